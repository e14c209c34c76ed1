"""DICOM fuzzing of the XA reader (`autocar info` and the read of `autocar reconstruct`): seeded mutations
of the bundled example runs, each run in a forked child with a 30 s limit.

A case passes when both targets end cleanly: ``autocar info FILE`` exits 0 or 2 without a traceback, and
:func:`stages.core.dicom_io.read_xa` (the full decode ``reconstruct`` does) returns or raises ``UserError``.
Anything else is a *traceback*; a child still running after the limit is a *hang*. Memory: each child's
peak resident set (VmHWM, reset at the fork) above its resident set at the fork.

Mutations (:func:`mutate`): truncation at a random length, random byte flips (in the header or anywhere),
deleting a geometry/pixel/size tag, corrupting a tag's value (garbage text, NaN, negative, huge, empty),
absurd sizes (NumberOfFrames 2e9/1e11, Rows/Columns 0/65535, BitsAllocated 1/7/64), a wrong transfer
syntax, a wrong modality, and combinations. Sources: both example runs (JPEG lossless, 49 frames) and two
small files derived from them (8 frames, uncompressed and JPEG lossless), so most cases decode quickly.

    python tests/fuzz_dicom.py --cases 3000 --seed 0      # -> docs/benchmarks/fuzz_dicom.md
    make fuzz                                                   # the same

A test harness, not a benchmark: the test suite runs a quick subset (tests/test_fuzz_dicom.py).
"""

from __future__ import annotations

import argparse
import copy
import io
import json
import os
import pickle
import random
import resource
import select
import signal
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

GEOMETRY_TAGS = ["PositionerPrimaryAngle", "PositionerSecondaryAngle", "DistanceSourceToDetector",
                 "DistanceSourceToPatient", "ImagerPixelSpacing"]
PIXEL_TAGS = ["Rows", "Columns", "NumberOfFrames", "BitsAllocated", "BitsStored", "HighBit", "SamplesPerPixel",
              "PixelRepresentation", "PhotometricInterpretation", "PixelData"]
OTHER_TAGS = ["Modality", "FrameTime", "CineRate", "RWaveTimeVector", "HeartRate", "FrameTimeVector"]
TEXT_VALUES = ["", "nan", "inf", "-1", "1e308", "abc", "12\\34\\56", "0", "-0", "999999999999"]
ABSURD = {"NumberOfFrames": ["2000000000", "100000000000", "0", "-5", "49.5"], "Rows": [0, 1, 65535],
          "Columns": [0, 1, 65535], "BitsAllocated": [1, 7, 64, 0], "BitsStored": [0, 40], "SamplesPerPixel": [0, 3, 9]}
WRONG_SYNTAX = ["1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.5", "1.2.840.10008.1.2.4.50",
                "1.2.840.10008.1.2.4.90", "1.2.3.4"]
TIMEOUT_S = 30.0


def sources(workdir: Path) -> list[Path]:
    """The example runs plus two small derived files (8 frames: uncompressed, and JPEG lossless)."""
    import numpy as np

    from stages.core.dicom_io import compress_lossless, read_xa, write_xa

    out = [REPO / "examples" / "run_a.dcm", REPO / "examples" / "run_b.dcm"]
    run = read_xa(out[0])
    frames = np.asarray(run.frames[:8], np.uint8)
    small = write_xa(workdir / "small_raw.dcm", frames, run.geometry, 66.7, heart_rate_bpm=63,
                     r_wave_times_ms=[0.0, 950.0], uid_seed="fuzz")
    jpeg = write_xa(workdir / "small_jpeg.dcm", frames, run.geometry, 66.7, uid_seed="fuzz-jpeg")
    compress_lossless(jpeg)
    return out + [small, jpeg]


def _dataset_bytes(ds) -> bytes:
    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=False)
    return buf.getvalue()


def mutate(rng: random.Random, raw: bytes, ds) -> tuple[str, bytes]:
    """One mutation of a source file (``raw`` its bytes, ``ds`` its parsed dataset): (description, bytes)."""
    import warnings

    with warnings.catch_warnings():  # pydicom warns about the invalid values we set on purpose
        warnings.simplefilter("ignore")
        return _mutate(rng, raw, ds)


def _mutate(rng: random.Random, raw: bytes, ds) -> tuple[str, bytes]:
    from pydicom.uid import UID

    kind = rng.choice(["truncate", "flip", "flip-header", "delete", "corrupt", "absurd", "syntax", "modality",
                       "combo", "delete", "corrupt", "absurd"])
    if kind == "truncate":
        n = rng.choice([rng.randrange(0, 400), rng.randrange(0, 4000), rng.randrange(0, len(raw))])
        return f"truncate to {n} bytes", raw[:n]
    if kind in ("flip", "flip-header"):
        data = bytearray(raw)
        hi = min(len(data), 3000) if kind == "flip-header" else len(data)
        k = rng.choice([1, 2, 8, 64])
        for _ in range(k):
            i = rng.randrange(0, hi)
            data[i] = rng.randrange(256)
        return f"{kind} {k} byte(s)", bytes(data)
    d = copy.deepcopy(ds)
    steps = []
    for _ in range(rng.choice([2, 3]) if kind == "combo" else 1):
        sub = rng.choice(["delete", "corrupt", "absurd"]) if kind == "combo" else kind
        if sub == "delete":
            tag = rng.choice(GEOMETRY_TAGS + PIXEL_TAGS + OTHER_TAGS)
            if tag in d:
                del d[tag]
            steps.append(f"delete {tag}")
        elif sub == "corrupt":
            tag = rng.choice(GEOMETRY_TAGS + ["NumberOfFrames", "FrameTime", "CineRate", "HeartRate"])
            value = rng.choice(TEXT_VALUES)
            try:
                setattr(d, tag, value)
                steps.append(f"{tag}={value!r}")
            except Exception:
                steps.append(f"{tag}={value!r} (rejected by pydicom)")
        elif sub == "absurd":
            tag = rng.choice(sorted(ABSURD))
            value = rng.choice(ABSURD[tag])
            setattr(d, tag, value)
            steps.append(f"{tag}={value!r}")
        elif sub == "syntax":
            uid = rng.choice(WRONG_SYNTAX)
            d.file_meta.TransferSyntaxUID = UID(uid)
            steps.append(f"TransferSyntaxUID={uid}")
        elif sub == "modality":
            value = rng.choice(["CT", "MR", "", "US"])
            d.Modality = value
            steps.append(f"Modality={value!r}")
    try:
        return "; ".join(steps), _dataset_bytes(d)
    except Exception as exc:  # pydicom cannot write it: fall back to a byte-level mutation of the same kind
        return f"{'; '.join(steps)} (unwritable: {type(exc).__name__}), truncated instead", raw[: len(raw) // 2]


def _targets(path: Path) -> dict:
    """Run both targets on one file in this (child) process; returns what happened."""
    from typer.testing import CliRunner

    from autocar_cli.main import app
    from stages.core.dicom_io import read_xa
    from stages.core.errors import UserError

    res = {}
    r = CliRunner().invoke(app, ["info", str(path)], catch_exceptions=True)
    text = (r.output or "") + (r.stderr if hasattr(r, "stderr") else "")
    bad = r.exit_code not in (0, 2) or "Traceback" in text or (r.exception is not None and not isinstance(r.exception, SystemExit))
    res["info"] = {"exit": r.exit_code, "ok": not bad,
                   "error": None if not bad else f"{type(r.exception).__name__}: {r.exception}" if r.exception else text[-300:]}
    try:
        read_xa(path)
        res["read"] = {"ok": True, "outcome": "read"}
    except UserError as exc:
        res["read"] = {"ok": True, "outcome": "refused", "message": str(exc)[:200]}
    except BaseException as exc:  # noqa: BLE001 — anything else is what the fuzz is looking for
        res["read"] = {"ok": False, "error": f"{type(exc).__name__}: {str(exc)[:300]}"}
    return res


def _status_kib(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


def _reset_peak() -> bool:
    """Reset this process's peak resident set (VmHWM): a forked child inherits its parent's peak otherwise."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def run_case(path: Path, timeout_s: float = TIMEOUT_S) -> dict:
    """Both targets in a forked child: outcome, seconds, peak memory above the parent's (MiB)."""
    rfd, wfd = os.pipe()
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # child
        os.close(rfd)
        exact = _reset_peak()
        base_kib = _status_kib("VmRSS")
        try:
            out = _targets(path)
        except BaseException as exc:  # noqa: BLE001
            out = {"harness": f"{type(exc).__name__}: {exc}"}
        peak = _status_kib("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        out["peak_kib"] = max(peak - base_kib, 0)
        with os.fdopen(wfd, "wb") as fh:
            fh.write(pickle.dumps(out))
        os._exit(0)
    os.close(wfd)
    chunks, hung = [], False
    deadline = t0 + timeout_s
    with os.fdopen(rfd, "rb") as fh:
        while True:
            left = deadline - time.perf_counter()
            if left <= 0:
                hung = True
                break
            ready, _, _ = select.select([fh], [], [], left)
            if ready:
                chunk = fh.read1(1 << 16)
                if not chunk:
                    break
                chunks.append(chunk)
    if hung:
        os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    seconds = time.perf_counter() - t0
    if hung:
        return {"hang": True, "seconds": seconds, "ok": False}
    try:
        out = pickle.loads(b"".join(chunks))
    except Exception:
        return {"ok": False, "seconds": seconds, "crash": "child died without a result"}
    out["seconds"] = seconds
    out["peak_mib"] = out.pop("peak_kib") / 1024
    out["ok"] = "harness" not in out and out["info"]["ok"] and out["read"]["ok"]
    out["hang"] = False
    return out


def fuzz(n_cases: int, seed: int = 0, workdir: Path | None = None, log=None) -> dict:
    """``n_cases`` seeded mutations over the sources; returns counts, failures and the worst times/memory."""
    import pydicom

    # import everything the children use once, before the forks
    import autocar_cli.main  # noqa: F401
    import stages.core.dicom_io  # noqa: F401

    tmp = tempfile.TemporaryDirectory() if workdir is None else None
    work = Path(tmp.name if tmp else workdir)
    work.mkdir(parents=True, exist_ok=True)
    srcs = sources(work)
    raws = [p.read_bytes() for p in srcs]
    parsed = [pydicom.dcmread(io.BytesIO(r)) for r in raws]
    rng = random.Random(seed)
    results = []
    case_file = work / "case.dcm"
    t_start = time.perf_counter()
    for i in range(n_cases):
        # most cases on the small sources, one in five on a full example run
        s = rng.choice([0, 1]) if rng.random() < 0.2 else rng.choice([2, 3])
        desc, data = mutate(rng, raws[s], parsed[s])
        case_file.write_bytes(data)
        out = run_case(case_file)
        out.update({"case": i, "source": srcs[s].name, "mutation": desc, "bytes": len(data)})
        if not out["ok"] and log:
            log(f"case {i} ({srcs[s].name}: {desc}): {json.dumps({k: out.get(k) for k in ('info', 'read', 'hang', 'crash')})}")
        results.append(out)
    wall = time.perf_counter() - t_start
    if tmp:
        tmp.cleanup()
    failures = [r for r in results if not r["ok"]]
    outcome = {}
    for r in results:
        if "read" in r:
            outcome[r["read"].get("outcome", "error")] = outcome.get(r["read"].get("outcome", "error"), 0) + 1
    return {"cases": len(results), "seed": seed, "tracebacks": sum(1 for r in failures if not r.get("hang")),
            "hangs": sum(1 for r in results if r.get("hang")), "failures": failures,
            "max_seconds": max((r["seconds"] for r in results), default=0.0),
            "peak_mib": max((r.get("peak_mib", 0.0) for r in results), default=0.0),
            "peak_case": max(results, key=lambda r: r.get("peak_mib", 0.0)) if results else None,
            "peak_per_file_mib": max((r.get("peak_mib", 0.0) / max(r["bytes"] / 2 ** 20, 1.0) for r in results), default=0.0),
            "largest_source_mib": max(len(r) for r in raws) / 2 ** 20,
            "read_outcomes": outcome, "wall_s": wall}


def write_doc(result: dict, path: Path, command: str) -> None:
    pc = result["peak_case"] or {}
    lines = [
        "# DICOM fuzzing of the XA reader",
        "",
        f"Command: `{command}` (OMP_NUM_THREADS=1; {time.strftime('%Y-%m-%d', time.gmtime())}; load average at start "
        f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs). Script: tests/fuzz_dicom.py.",
        "",
        "Each case is one seeded mutation of an example run (or of an 8-frame file derived from one); both "
        "`autocar info FILE` and the full read of `autocar reconstruct` (`stages.core.dicom_io.read_xa`) run on it in "
        "a forked child with a 30 s limit.",
        "",
        "| figure | value | target |",
        "|---|---|---|",
        f"| cases | {result['cases']} (seed {result['seed']}) | a few thousand |",
        f"| tracebacks (anything but exit 0/2 from `info`, or an exception other than UserError from the read) | {result['tracebacks']} | 0 |",
        f"| hangs over {TIMEOUT_S:.0f} s | {result['hangs']} | 0 |",
        f"| slowest case | {result['max_seconds']:.2f} s | < 30 s |",
        f"| peak memory of a case above the parent process | {result['peak_mib']:.0f} MiB "
        f"({pc.get('source', '?')}: {pc.get('mutation', '?')}) | bounded by the file size |",
        f"| largest source file | {result['largest_source_mib']:.1f} MiB | |",
        f"| peak memory per MiB of file (files under 1 MiB counted as 1 MiB) | {result['peak_per_file_mib']:.0f} | bounded |",
        f"| outcomes of the read | {', '.join(f'{k} {v}' for k, v in sorted(result['read_outcomes'].items()))} | |",
        f"| wall time | {result['wall_s']:.0f} s | |",
        "",
        "The peak memory is that of the full decode of an intact-enough run (a 49-frame 256² run: the decoded "
        "pixels, their float32 copy and pydicom's buffers), whatever the header claims: a claim the pixel data "
        "does not back is refused before anything is allocated.",
    ]
    if result["failures"]:
        lines += ["", "## Failures", ""]
        for r in result["failures"][:50]:
            lines.append(f"- case {r['case']} ({r['source']}: {r['mutation']}): "
                         f"{json.dumps({k: r.get(k) for k in ('info', 'read', 'hang', 'crash')})}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "fuzz_dicom.md")
    args = ap.parse_args(argv)
    import logging

    logging.disable(logging.CRITICAL)  # the children's warnings are not the result
    res = fuzz(args.cases, args.seed, log=lambda m: print(m, flush=True))
    cmd = f"python tests/fuzz_dicom.py --cases {args.cases} --seed {args.seed}"
    write_doc(res, args.out, cmd)
    print(f"{res['cases']} cases: {res['tracebacks']} tracebacks, {res['hangs']} hangs, slowest {res['max_seconds']:.1f} s, "
          f"peak {res['peak_mib']:.0f} MiB, {res['wall_s']:.0f} s -> {args.out}")
    return 0 if not res["failures"] else 1


if __name__ == "__main__":
    sys.exit(main())

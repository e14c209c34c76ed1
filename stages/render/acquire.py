"""Simulated two-view XA acquisitions of a beating, breathing coronary tree (``autocar render --xa``).

Reads: a prepared case (``autocar.prepared-case``) and a pose model (``autocar.pose-model``).
Writes, into an output folder per case:

* ``run_a.dcm``, ``run_b.dcm`` — real multi-frame XA DICOMs (:func:`stages.core.dicom_io.write_xa`) with
  full geometry (PositionerPrimary/SecondaryAngle, SID, SOD, ImagerPixelSpacing), timing (FrameTime,
  CineRate), HeartRate and RWaveTimeVector (R-wave times in ms from the run's first frame, from the R wave
  before the first frame to the one after the last, so the first value is ≤ 0).
  The two runs are acquired one after the other, from two different clusters of the pose model
  (:meth:`PoseModel.sample_pair`), at different start times on one continuous heart/breathing clock.
* ``truth.zarr`` — the sidecar ground truth, kind ``"autocar.xa-truth"`` (schema 1)::

    attrs: standard header + case_id, case (path), seed, motion (HeartMotion dict, reproduces every
           frame's 3D geometry), runs {"a"|"b": {dicom, start_time_s, frame_time_ms, n_frames, geometry
           {alpha, beta, sid, sod, spacing, rows, cols}, style (XAStyle), bolus (BolusModel)}},
           n_keyframes, n_correspondences
    centreline/reference_nodes   N×3 float32  end-diastolic (reference) nodes, mm LPS
    centreline/radius            N float32
    centreline/edges             E×2 int32
    runs/<a|b>/nodes             T×N×3 float32  centreline nodes at each frame
    runs/<a|b>/phase             T float64   cardiac phase in [0, 1) (0 = end-diastole)
    runs/<a|b>/resp              T float64   respiratory state in [0, 1]
    runs/<a|b>/time_s            T float64   time on the common clock (s)
    runs/<a|b>/concentration     T float64   contrast concentration at the ostium
    runs/<a|b>/masks             T×H×W uint8 2D vessel masks (exact silhouettes of the deformed lumen)
    keyframes/pairs              K×2 int32   (frame in run a, frame in run b) at matched cardiac phase
    keyframes/phase_error        K float64   circular phase difference of each pair
    keyframes/ref_points         K×M×3 float32  correspondence points in the reference configuration
    keyframes/points_a, points_b K×M×3 float32  the same points at the two frames (mm)
    keyframes/uv_a, uv_b         K×M×2 float64  their (row, col) pixel positions in the two runs

  Correspondence *m* of pair *k*: ``HeartMotion.apply(ref_points[k, m], phase, resp)`` at the frame's
  phase/resp, projected with the run's camera, gives ``uv`` to floating-point precision.

Frames: :class:`stages.render.xa.XAScene`; motion: :mod:`stages.render.motion`.
"""

from __future__ import annotations

import logging
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..core.errors import UserError
from ..core.geometry import Camera
from .motion import HeartMotion, contraction, sample_motion
from .pairs import case_from, pose_model_from, visible_fraction
from .raster import rasterise_lumen
from .xa import BolusModel, XAScene, default_catheter_path, node_path_distance, sample_style

log = logging.getLogger(__name__)

TRUTH_KIND = "autocar.xa-truth"
TRUTH_SCHEMA = 1

__all__ = ["simulate_acquisition", "load_truth", "TRUTH_KIND", "check_visibility"]


def check_visibility(points, camera: Camera, what: str, warn_below: float = 1.0, refuse_below: float = 0.5) -> float:
    """Fraction of ``points`` inside the image: warn if below ``warn_below``, UserError below ``refuse_below``."""
    frac = visible_fraction(points, camera, margin_px=0.0)
    if frac < refuse_below:
        raise UserError(f"{what}: only {frac:.0%} of the tree is inside the {camera.rows}×{camera.cols} field of view "
                        f"(need at least {refuse_below:.0%}); move the tree nearer the isocentre or use a larger detector")
    if frac < warn_below:
        log.warning("%s: %.0f%% of the tree is inside the field of view", what, 100 * frac)
    return frac


def _rounded_geometry(pose, size):
    """The pose at ``size``² with values rounded as the DICOM writer stores them (so truth = file)."""
    from ..core.dicom_io import XAGeometry

    sr = pose.spacing[0] * pose.rows / size
    sc = pose.spacing[1] * pose.cols / size
    return XAGeometry(round(pose.alpha, 4), round(pose.beta, 4), round(pose.sid, 4), round(pose.sod, 4),
                      (float(f"{sr:.8g}"), float(f"{sc:.8g}")), size, size)


def _densify(nodes: np.ndarray, edges: np.ndarray, step: float) -> np.ndarray:
    """Centreline points every ~``step`` mm along the edges (candidate correspondence locations)."""
    out = [nodes]
    for a, b in np.asarray(edges).reshape(-1, 2):
        n = int(np.linalg.norm(nodes[b] - nodes[a]) // step)
        if n > 1:
            t = (np.arange(1, n) / n)[:, None]
            out.append(nodes[a] + t * (nodes[b] - nodes[a]))
    return np.concatenate(out)


def _farthest_points(P: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    idx = [int(rng.integers(len(P)))]
    d = np.linalg.norm(P - P[idx[0]], axis=1)
    for _ in range(min(m, len(P)) - 1):
        i = int(np.argmax(d))
        idx.append(i)
        d = np.minimum(d, np.linalg.norm(P - P[i], axis=1))
    return np.array(idx)


def simulate_acquisition(case, pose_model, out_dir, seed: int, *, size: int = 512, n_frames: int = 42,
                         fps: float = 15.0, bits: int = 8, n_keyframes: int = 7, n_correspondences: int = 60,
                         catheter: bool | None = None, breath_hold: bool | None = None, min_visible: float = 0.5,
                         progress=None, n_runs: int = 2) -> dict:
    """Simulate two XA runs of one case; write run_a.dcm, run_b.dcm and truth.zarr into ``out_dir``.

    ``n_runs`` 3: also a third run, ``run_c.dcm``, from a third pose cluster, acquired in the pause between the
    two (a study's further run of the same injection side); the truth gains ``runs/c`` and, per key frame, run C's
    frame of the nearest cardiac phase (``keyframes/frames_c``) with the annotated points' projections in it
    (``keyframes/uv_c``). Runs A and B are the same as with two runs (run C draws from its own random stream)."""
    if n_runs not in (2, 3):
        raise UserError(f"render: {n_runs} runs per case; choose 2 or 3")
    from scipy.spatial import cKDTree

    from ..core.artefacts import write_zarr
    from ..core.dicom_io import write_xa

    case = case_from(case)
    model = pose_model_from(pose_model)
    out_dir = Path(out_dir)
    rng = np.random.default_rng(seed)
    V, F = case.vertices.astype(float), case.faces
    nodes = case.nodes.astype(float)
    pts_src = case.truth.points.astype(float) if case.truth is not None else _densify(nodes, case.edges, 1.0)
    # poses: two clusters; redraw (bounded) until the tree is well inside both fields of view
    best = None
    for _ in range(30):
        pa, pb = model.sample_pair(rng)
        ga, gb = _rounded_geometry(pa, size), _rounded_geometry(pb, size)
        vis = min(visible_fraction(nodes, ga.camera(), 0.0), visible_fraction(nodes, gb.camera(), 0.0))
        if best is None or vis > best[0]:
            best = (vis, pa, pb, ga, gb)
        if vis >= 0.98:
            break
    _, pa, pb, ga, gb = best
    cams = {"a": ga.camera(), "b": gb.camera()}
    for k in "ab":
        check_visibility(nodes, cams[k], f"case {case.case_id} run {k}", refuse_below=min_visible)
    frame_dt = 1.0 / fps
    run_len = n_frames * frame_dt
    start = {"a": float(rng.uniform(0.0, 1.0))}
    start["b"] = start["a"] + run_len + float(rng.uniform(4.0, 15.0))  # second run after a pause
    motion = sample_motion(nodes, rng, case.heart, duration=start["b"] + run_len + 1.0, breath_hold=breath_hold)
    dist, root = node_path_distance(nodes, case.edges)
    near = cKDTree(nodes).query(V)[1]
    cath_rng = np.random.default_rng([seed, 7])
    cath_path = default_catheter_path(nodes[root], np.asarray(motion.centre), np.asarray(motion.long_axis), cath_rng)
    cath_s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(cath_path, axis=0), axis=1))])
    cath_w = np.exp(-cath_s / 25.0)[:, None]  # the tip rides with the heart, the shaft with respiration
    rv = np.asarray(motion.resp_vector, float)

    run_list = [("a", pa, ga, rng), ("b", pb, gb, rng)]
    if n_runs == 3:
        # run C from its own random stream, so that runs A and B (and everything drawn after them) are unchanged
        rng_c = np.random.default_rng([seed, 3])
        pc = gc = None
        for _ in range(30):
            pc = model.sample_other(rng_c, exclude_clusters=(pa.cluster, pb.cluster))
            gc = _rounded_geometry(pc, size)
            if visible_fraction(nodes, gc.camera(), 0.0) >= 0.98:
                break
        cams["c"] = gc.camera()
        check_visibility(nodes, cams["c"], f"case {case.case_id} run c", refuse_below=min_visible)
        # in the pause between runs A and B (the motion was drawn to cover them); with no room, beside run A
        room = start["b"] - start["a"] - 2 * run_len
        start["c"] = start["a"] + run_len + 0.5 * room if room > 0 else start["a"]
        run_list.append(("c", pc, gc, rng_c))
    runs: dict[str, dict] = {}
    for k, pose, geom, rng_k in run_list:
        style = sample_style(rng_k, bits=bits, catheter=catheter)
        bolus = BolusModel(t_start=float(rng_k.uniform(0.1, 0.4)), rise=float(rng_k.uniform(0.4, 0.8)),
                           t_washout=float(run_len * rng_k.uniform(0.7, 0.85)),
                           washout_tau=float(rng_k.uniform(0.6, 1.2)), speed=float(rng_k.uniform(150, 300)))
        scene = XAScene(cams[k], style, np.asarray(motion.centre), np.asarray(motion.long_axis),
                        seed=int(rng_k.integers(2**31)), catheter_path=cath_path,
                        anatomy_shift=rng_k.normal(0, 5.0, 3))
        t = start[k] + np.arange(n_frames) * frame_dt
        phase = motion.phase_at(t)
        resp = motion.resp_state(t)
        frames, masks, node_t, conc = [], [], [], []
        for i in range(n_frames):
            Vi = motion.apply(V, phase[i], resp[i])
            c_nodes = bolus.at(t[i] - start[k] - dist / bolus.speed)
            fc = c_nodes[near][F].mean(axis=1)
            cath_now = cath_w * motion.apply(cath_path, phase[i], resp[i]) + (1 - cath_w) * (cath_path + resp[i] * rv)
            # one raster pass gives the truth silhouette and the iodine path length of the frame
            mask, path_length = rasterise_lumen(Vi, F, cams[k], face_weight=fc)
            g = scene.frame(Vi, F, fc, float(contraction(phase[i], motion.t_systole, motion.t_relax)), float(resp[i]),
                            rv, cath_now, frame_index=i, path_length=path_length)
            frames.append(scene.quantise(g))
            masks.append(mask.astype(np.uint8))
            node_t.append(motion.apply(nodes, phase[i], resp[i]).astype(np.float32))
            conc.append(float(bolus.at(t[i] - start[k])))
            if progress is not None:
                progress()
        runs[k] = {"pose": pose, "geometry": geom, "style": style, "bolus": bolus, "time": t, "phase": phase,
                   "resp": resp, "frames": np.stack(frames), "masks": np.stack(masks), "nodes": np.stack(node_t),
                   "conc": np.array(conc)}

    # key-frame pairs: well-filled frames of run a spread over the run, each with the run-b frame of
    # the nearest cardiac phase (the runs are not simultaneous, so phase is what matches)
    ok_a = np.flatnonzero(runs["a"]["conc"] >= 0.7)
    ok_b = np.flatnonzero(runs["b"]["conc"] >= 0.7)
    if len(ok_a) < n_keyframes or len(ok_b) == 0:
        ok_a, ok_b = np.arange(n_frames), np.arange(n_frames)
    pick_a = ok_a[np.linspace(0, len(ok_a) - 1, n_keyframes).round().astype(int)]
    pairs, perr = [], []
    for i in pick_a:
        d = np.abs(runs["b"]["phase"][ok_b] - runs["a"]["phase"][i])
        d = np.minimum(d, 1 - d)
        j = ok_b[int(np.argmin(d))]
        pairs.append((int(i), int(j)))
        perr.append(float(d.min()))
    frames_c = []
    if "c" in runs:  # run C's frame of the nearest phase to each key frame's run-A frame
        ok_c = np.flatnonzero(runs["c"]["conc"] >= 0.7)
        ok_c = ok_c if len(ok_c) else np.arange(n_frames)
        for i, _ in pairs:
            d = np.abs(runs["c"]["phase"][ok_c] - runs["a"]["phase"][i])
            frames_c.append(int(ok_c[int(np.argmin(np.minimum(d, 1 - d)))]))
    # correspondences: points spread over the tree, inside both images at both frames
    M = n_correspondences
    ref_pts, pts_a, pts_b, uv_a, uv_b, uv_c = [], [], [], [], [], []
    for n_kf, (i, j) in enumerate(pairs):
        Pa = motion.apply(pts_src, runs["a"]["phase"][i], runs["a"]["resp"][i])
        Pb = motion.apply(pts_src, runs["b"]["phase"][j], runs["b"]["resp"][j])
        ua, ub = cams["a"].project(Pa), cams["b"].project(Pb)
        good = np.flatnonzero(cams["a"].in_image(ua, margin=4) & cams["b"].in_image(ub, margin=4))
        if len(good) < M:
            raise UserError(f"case {case.case_id}: only {len(good)} tree points visible in both runs, need {M}")
        sel = good[_farthest_points(pts_src[good], M, rng)]
        ref_pts.append(pts_src[sel])
        pts_a.append(Pa[sel])
        pts_b.append(Pb[sel])
        uv_a.append(ua[sel])
        uv_b.append(ub[sel])
        if frames_c:
            c = frames_c[n_kf]
            uv_c.append(cams["c"].project(motion.apply(pts_src[sel], runs["c"]["phase"][c], runs["c"]["resp"][c])))

    out_dir.mkdir(parents=True, exist_ok=True)
    rr_starts = np.concatenate([[0.0], np.cumsum(motion.rr_intervals)]) - motion.phase0 * motion.rr_intervals[0]
    from pydicom.uid import generate_uid

    study_uid = generate_uid(entropy_srcs=[f"autocar-sim-{seed}-study"])  # both runs: one study
    run_attrs = {}
    for k in runs:
        r = runs[k]
        t0, t1 = r["time"][0], r["time"][-1]
        # R waves around the run (the one before its first frame and the one after its last included,
        # so the vector always brackets the run and never has a single value)
        before = rr_starts[rr_starts <= t0]
        after = rr_starts[rr_starts > t1]
        sel = (rr_starts >= (before[-1] if len(before) else t0)) & (rr_starts <= (after[0] if len(after) else t1))
        rwave = (rr_starts[sel] - t0) * 1000.0
        path = out_dir / f"run_{k}.dcm"
        write_xa(path, r["frames"], r["geometry"], frame_dt * 1000.0, bits_stored=bits,
                 patient_id=f"AUTOCAR-SIM-{case.case_id}", series_description=f"simulated run {k} (seed {seed})",
                 heart_rate_bpm=motion.heart_rate_bpm, r_wave_times_ms=rwave.tolist(),
                 study_uid=study_uid, uid_seed=f"autocar-sim-{seed}-run-{k}")
        run_attrs[k] = {"dicom": path.name, "start_time_s": float(t0), "frame_time_ms": frame_dt * 1000.0,
                        "n_frames": n_frames, "geometry": r["geometry"].as_dict(), "cluster": int(r["pose"].cluster),
                        "style": asdict(r["style"]), "bolus": asdict(r["bolus"])}
    params = {"seed": seed, "size": size, "n_frames": n_frames, "fps": fps, "bits": bits, "n_keyframes": n_keyframes,
              "n_correspondences": M}
    extra = {"case_id": case.case_id, "case": str(case.path) if case.path else case.case_id, "seed": seed,
             "motion": motion.to_dict(), "runs": run_attrs, "n_keyframes": len(pairs), "n_correspondences": M}
    with write_zarr(out_dir / "truth.zarr", kind=TRUTH_KIND, schema_version=TRUTH_SCHEMA, stage="render",
                    inputs=[extra["case"]], parameters=params, extra_attrs=extra) as g:
        cl = g.require_group("centreline")
        cl.create_array("reference_nodes", data=nodes.astype(np.float32))
        cl.create_array("radius", data=case.radius.astype(np.float32))
        cl.create_array("edges", data=case.edges.astype(np.int32))
        for k in runs:
            r = runs[k]
            rg = g.require_group(f"runs/{k}")
            rg.create_array("nodes", data=r["nodes"])
            rg.create_array("phase", data=r["phase"])
            rg.create_array("resp", data=r["resp"])
            rg.create_array("time_s", data=r["time"])
            rg.create_array("concentration", data=r["conc"])
            rg.create_array("masks", data=r["masks"], chunks=(1, size, size))
        kg = g.require_group("keyframes")
        kg.create_array("pairs", data=np.asarray(pairs, np.int32))
        kg.create_array("phase_error", data=np.asarray(perr))
        kg.create_array("ref_points", data=np.stack(ref_pts).astype(np.float32))
        kg.create_array("points_a", data=np.stack(pts_a).astype(np.float32))
        kg.create_array("points_b", data=np.stack(pts_b).astype(np.float32))
        kg.create_array("uv_a", data=np.stack(uv_a))
        kg.create_array("uv_b", data=np.stack(uv_b))
        if frames_c:
            kg.create_array("frames_c", data=np.asarray(frames_c, np.int32))
            kg.create_array("uv_c", data=np.stack(uv_c))
    return {**({"run_c": out_dir / "run_c.dcm", "frames_c": frames_c} if frames_c else {}),"out_dir": out_dir, "run_a": out_dir / "run_a.dcm", "run_b": out_dir / "run_b.dcm",
            "truth": out_dir / "truth.zarr", "pairs": pairs, "phase_error": perr,
            "poses": (pa.as_dict(), pb.as_dict()), "heart_rate_bpm": motion.heart_rate_bpm}


def load_truth(path) -> dict:
    """Read an ``autocar.xa-truth`` artefact into a dict of arrays + ``motion`` (HeartMotion) + attrs."""
    from ..core.artefacts import read_zarr

    g = read_zarr(path, kind=TRUTH_KIND, schema_version=TRUTH_SCHEMA)
    attrs = dict(g.attrs)
    out = {"attrs": attrs, "motion": HeartMotion.from_dict(attrs["motion"])}
    for name in ("reference_nodes", "radius", "edges"):
        out[name] = g[f"centreline/{name}"][...]
    for k in "ab":
        out[k] = {n: g[f"runs/{k}/{n}"][...] for n in ("nodes", "phase", "resp", "time_s", "concentration")}
        out[k]["masks"] = g[f"runs/{k}/masks"]  # lazy: T×H×W
    out["keyframes"] = {n: g[f"keyframes/{n}"][...] for n in ("pairs", "phase_error", "ref_points", "points_a",
                                                               "points_b", "uv_a", "uv_b")}
    if "c" in attrs["runs"]:  # a three-run case (render re --runs 3)
        out["c"] = {n: g[f"runs/c/{n}"][...] for n in ("nodes", "phase", "resp", "time_s", "concentration")}
        out["c"]["masks"] = g["runs/c/masks"]
        out["keyframes"].update({n: g[f"keyframes/{n}"][...] for n in ("frames_c", "uv_c")})
    return out

"""Training/test frames for the 2D vessel segmenter, rendered by the synthetic X-ray engine.

Reads: prepared cases (``autocar.prepared-case``; by default the procedural training trees in
``data/train_cases``, seeds < 1 000 000, disjoint from data-se / data-re / example seeds). Writes: one
``.npz`` per case under ``data/seg/<split>/`` (kind ``"autocar.seg-frames"``, schema 2) with

    frames  N×H×W uint8   simulated XA frames (vessels dark), :class:`stages.render.xa.XAScene`
    masks   N×H×W uint8   ground truth: *visible* vessel = pixels of the collimator's open field
                          (:attr:`XAScene.open_field`) whose contrast-weighted iodine path length ∫c·dl
                          through the lumen is ≥ ``VISIBLE_MM`` (0.3 mm) — :func:`visible_vessel`
    spacing N float32     isocentre mm per pixel of each frame

Each frame is a fresh random view of the tree: a C-arm pose from the default pose model, a random
cardiac phase and respiratory state of a random heart motion, a random imaging style (photons, iodine
attenuation, blur, anatomy strength, catheter, collimator) and a random moment of the contrast bolus
(mostly filled, sometimes arriving or washing out, ~8 % before any contrast: an empty mask). A quarter
of the scenes have faint background anatomy, closer to a bench-top phantom than to a patient.

The ground truth is contrast-weighted on purpose: a branch that holds no iodine yet is not visible and
must not be labelled, and the catheter (contrast-filled but not a coronary) is not labelled either.
Schema 2 also leaves out vessel behind the collimator blades (3 % transmission: no image there); schema 1
labelled it, which counted invisible vessel along the dark border as missed in the test frames.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

KIND = "autocar.seg-frames"
SCHEMA = 2  # 2: truth restricted to the collimator's open field
VISIBLE_MM = 0.3  # contrast-weighted iodine path length (mm) above which a pixel shows vessel

__all__ = ["render_case_frames", "build_split", "load_split", "VISIBLE_MM", "default_split_cases", "visible_vessel"]


def default_split_cases(folder="data/train_cases") -> dict:
    """Training trees vs held-out test trees: cases 0–23 train, 24–31 test (both sides).

    The test range is closed: the folder grows with the 3D model's training set, the held-out frames
    must not."""
    folder = Path(folder)
    paths = sorted(folder.glob("case_*_*.zarr"))
    split = {"train": [], "test": []}
    for p in paths:
        idx = int(p.name.split("_")[1])
        if idx < 32:
            split["test" if idx >= 24 else "train"].append(p)
    return split


def visible_vessel(path_length: np.ndarray, open_field: np.ndarray) -> np.ndarray:
    """The one definition of the segmentation truth: H×W uint8, 1 where a frame shows vessel.

    ``path_length``: contrast-weighted lumen path length ∫c·dl (mm) per pixel; ``open_field``: the
    collimator's open field. Vessel without iodine (∫c·dl < ``VISIBLE_MM``) or behind the blades is invisible.
    """
    return ((np.asarray(path_length) >= VISIBLE_MM) & np.asarray(open_field, bool)).astype(np.uint8)


def render_case_frames(case_path, seed: int, n_scenes: int = 3, frames_per_scene: int = 4, size: int = 512):
    """Render ``n_scenes × frames_per_scene`` random frames of one case → (frames, masks, spacing)."""
    from ..poses import PoseModel
    from ..render.motion import contraction, sample_motion
    from ..render.pairs import case_from, simplified_for_rendering, visible_fraction
    from ..render.raster import rasterise_path_length
    from ..render.xa import BolusModel, XAScene, default_catheter_path, node_path_distance, sample_varied_style

    rng = np.random.default_rng(seed)
    case = simplified_for_rendering(case_from(case_path), max_faces=60_000)
    V, F, nodes = case.vertices.astype(float), case.faces, case.nodes.astype(float)
    model = PoseModel.default(seed=int(seed) % 1000)
    dist, root = node_path_distance(nodes, case.edges)
    from scipy.spatial import cKDTree

    near = cKDTree(nodes).query(V)[1]
    frames, masks, spacing = [], [], []
    for s in range(n_scenes):
        # a pose that keeps most of the tree in view
        best = None
        for _ in range(10):
            pose = model.sample_pair(rng)[int(rng.integers(2))]
            cam = pose.camera(size, size)
            vis = visible_fraction(nodes, cam, 0.0)
            if best is None or vis > best[0]:
                best = (vis, cam)
            if vis > 0.95:
                break
        cam = best[1]
        motion = sample_motion(nodes, rng, case.heart, duration=6.0)
        style = sample_varied_style(rng)  # a quarter phantom-like: little anatomy, smooth background
        bolus = BolusModel(t_start=0.0, rise=float(rng.uniform(0.4, 0.8)), t_washout=float(rng.uniform(1.8, 2.6)),
                           washout_tau=float(rng.uniform(0.6, 1.2)), speed=float(rng.uniform(150, 300)))
        scene = XAScene(cam, style, np.asarray(motion.centre), np.asarray(motion.long_axis),
                        seed=int(rng.integers(2**31)), anatomy_shift=rng.normal(0, 5.0, 3),
                        catheter_path=default_catheter_path(nodes[root], np.asarray(motion.centre),
                                                            np.asarray(motion.long_axis), rng))
        rv = np.asarray(motion.resp_vector, float)
        for f in range(frames_per_scene):
            u = rng.random()
            # mostly opacified; some arriving / washing-out frames; a few before any contrast
            t = -0.3 if u < 0.08 else (float(rng.uniform(0.1, 0.9)) if u < 0.25 else float(rng.uniform(0.9, 2.8)))
            phase, resp = float(rng.random()), float(rng.random())
            Vi = motion.apply(V, phase, resp)
            conc = bolus.at(t - dist / bolus.speed)
            fc = conc[near][F].mean(axis=1)
            cath = motion.apply(scene.catheter_path, phase, resp) if style.catheter else None
            g = scene.frame(Vi, F, fc, float(contraction(phase, motion.t_systole, motion.t_relax)), resp, rv, cath,
                            frame_index=f)
            L = rasterise_path_length(Vi, F, cam, face_weight=fc)
            frames.append(scene.quantise(g))
            masks.append(visible_vessel(L, scene.open_field))
            spacing.append(cam.isocentre_spacing)
    return np.stack(frames), np.stack(masks), np.asarray(spacing, np.float32)


def build_split(out="data/seg", cases_folder="data/train_cases", split: str = "train", n_scenes: int = 3,
                frames_per_scene: int = 4, size: int = 512, seed: int = 500_000) -> list[Path]:
    """Render every case of ``split`` into ``out/split/<case>.npz`` (cases already written in the current
    schema are kept; older ones are rendered again — same seeds, same frames, the current truth)."""
    from ..core.artefacts import artefact_attributes, save_npz

    out = Path(out) / split
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, path in enumerate(default_split_cases(cases_folder)[split]):
        dst = out / (Path(path).stem + ".npz")
        if not dst.exists() or artefact_attributes(dst).get("schema_version") != SCHEMA:
            case_seed = seed + (100_000 if split == "test" else 0) + i
            fr, mk, sp = render_case_frames(path, case_seed, n_scenes, frames_per_scene, size)
            save_npz(dst, {"frames": fr, "masks": mk, "spacing": sp}, kind=KIND, schema_version=SCHEMA,
                     stage="segment")
            log.info("%s: %d frames, vessel fraction %.3f", dst, len(fr), mk.mean())
        written.append(dst)
    return written


def load_split(folder) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All frames/masks/spacings of one split folder, concatenated."""
    from ..core.artefacts import load_npz

    fr, mk, sp = [], [], []
    for p in sorted(Path(folder).glob("*.npz")):
        arrays, _ = load_npz(p, kind=KIND, schema_version=SCHEMA)
        fr.append(arrays["frames"])
        mk.append(arrays["masks"])
        sp.append(arrays["spacing"])
    if not fr:
        from ..core.errors import UserError

        raise UserError(f"{folder}: no segmentation training frames (*.npz); run `make train-seg`")
    return np.concatenate(fr), np.concatenate(mk), np.concatenate(sp)


if __name__ == "__main__":  # python -m stages.segment.data [split ...]
    import sys

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    for sp in sys.argv[1:] or ["test", "train"]:
        # test: 16 unseen trees × 2 scenes × 3 frames = 96 frames; train: 48 trees × 3 × 4 = 576
        build_split(split=sp, n_scenes=2 if sp == "test" else 3, frames_per_scene=3 if sp == "test" else 4)

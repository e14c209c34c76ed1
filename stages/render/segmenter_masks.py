"""The 2D segmenter's own masks of a training pair (a training augmentation of the SBP network).

Reads the shipped segmenter weights (``stages/weights/seg.pt``, through :mod:`stages.segment.infer`);
writes nothing. At inference the SBP network sees U-Net masks of X-ray frames, not exact silhouettes.
:mod:`stages.render.mask_noise` imitates the U-Net's errors by hand; this module gives the network the
real thing: each view of a rendered pair becomes a simulated XA frame (:class:`stages.render.xa.XAScene`,
the engine data-re is rendered with) of exactly the geometry the silhouette shows — the same camera,
the same (phase-moved, TPS-warped) lumen — and the U-Net segments it. The 3D ground truth is unchanged,
so the network learns what the segmenter's breaks, misses and false positives mean in 3D.

Each view draws its own imaging style (:func:`stages.render.xa.sample_varied_style`: the styles of
the segmenter's training frames, a quarter of them phantom-like with faint anatomy); the contrast is
that of a key frame (opacified, 75–100 % of full concentration). Every draw comes from the
``numpy.random.Generator`` passed in, so a training pair stays a pure function of its seed.
"""

from __future__ import annotations

import numpy as np

__all__ = ["segmenter_masks", "xa_frame_of_view"]


def xa_frame_of_view(vertices, faces, camera, rng: np.random.Generator, heart_centre, heart_axis,
                     offset_rc=None) -> np.ndarray:
    """One simulated uint8 XA frame (vessels dark) of the lumen mesh as ``camera`` sees it; ``offset_rc``
    (V×2 px) moves the projected vertices as :func:`stages.render.raster.rasterise_mask` does."""
    from .raster import rasterise_path_length
    from .xa import XAScene, sample_varied_style

    # the segmenter's training styles (a quarter phantom-like); no catheter: its path needs the heart's motion
    style = sample_varied_style(rng, catheter=False)
    scene = XAScene(camera, style, np.asarray(heart_centre, float), np.asarray(heart_axis, float),
                    seed=int(rng.integers(2**31)), anatomy_shift=rng.normal(0, 5.0, 3))
    conc = float(rng.uniform(0.75, 1.0))
    L = rasterise_path_length(vertices, faces, camera, face_weight=np.full(len(faces), conc), offset_rc=offset_rc)
    # a random cardiac contraction and breathing state of the background (the heart silhouette, diaphragm)
    grey = scene.frame(vertices, faces, None, float(rng.uniform(0, 1)), float(rng.uniform(0, 1)),
                       (0.0, 0.0, 10.0), path_length=L)
    return scene.quantise(grey)


def segmenter_masks(sample: dict, case, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(mask_a, mask_b): the U-Net's masks of XA frames of a :func:`stages.render.pairs.render_pair`
    sample of ``case`` (the sample records the lumen vertices and view b's warp offsets it rasterised)."""
    from ..segment.infer import segment_frames
    from .motion import heart_frame

    faces = case.faces
    heart_centre, heart_axis = heart_frame(case.nodes, case.heart)
    heart_centre = heart_centre + sample["translation"]  # the pair moved the whole case

    frames = np.stack([
        xa_frame_of_view(sample["vertices_a"], faces, sample["camera_a"], rng, heart_centre, heart_axis),
        xa_frame_of_view(sample["vertices_b"], faces, sample["camera_b"], rng, heart_centre, heart_axis,
                         offset_rc=sample["offset_b"]),
    ])
    _, masks = segment_frames(frames, method="unet")
    return masks[0].astype(bool), masks[1].astype(bool)

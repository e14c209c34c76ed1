"""Sparse backward projection (SBP): the network (:mod:`.model`), its loss (:mod:`.loss`) and its training
(:mod:`.train`, the ``autocar train`` stage, which makes the shipped weights ``stages/weights/sbp.pt``).

Reads: two vessel masks + cameras (inference), or prepared cases + a pose model (training, via
:mod:`stages.sbp.train`). Writes: nothing itself; :mod:`stages.sbp.train` writes checkpoints, inference
callers write ``autocar.sparse-prediction`` artefacts.
"""

from .model import SBPConfig, SBPNet, PairInput, active_pixels, candidate_voxels, check_pair, prepare_pair, signed_edt_mm

__all__ = ["SBPConfig", "SBPNet", "PairInput", "active_pixels", "candidate_voxels", "check_pair", "prepare_pair",
           "signed_edt_mm"]

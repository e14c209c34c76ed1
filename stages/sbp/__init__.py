"""Sparse backward projection (SBP) network, its loss, and the shipped weights.

Reads: two vessel masks + cameras (inference), or prepared cases + a pose model (training, via
:mod:`stages.train`). Writes: nothing itself; :mod:`stages.train` writes checkpoints, inference
callers write ``autocar.sparse-prediction`` artefacts.
"""

from .model import SBPConfig, SBPNet, PairInput, active_pixels, candidate_voxels, check_pair, prepare_pair, signed_edt_mm

__all__ = ["SBPConfig", "SBPNet", "PairInput", "active_pixels", "candidate_voxels", "check_pair", "prepare_pair",
           "signed_edt_mm"]

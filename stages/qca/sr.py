"""QCA as a DICOM Structured Report: ``qca_sr.dcm`` beside qca.json, so the figures can go into the study in a PACS.

A Comprehensive 3D SR (highdicom) holding a TID 1500 Measurement Report: the source runs are its evidence
(their Study, Series and SOP Instance UIDs, in the Current Requested Procedure Evidence Sequence, or Pertinent
Other Evidence when a run belongs to another study) and every measurement group names the frames of both
runs it was measured on. One TID 1501 group per vessel (length, mean and minimal lumen diameter) and one per
lesion (%DS, minimal lumen diameter, reference diameter, lesion length, distance from the vessel's origin).
The codes (DICOM PS3.16 and SNOMED CT, as pydicom's code dictionary lists them) are in :data:`CODES`; the
two concepts no standard code expresses use the local scheme ``99AUTOCAR`` (docs/QCA.md lists them all).

Only runs read from DICOM files have UIDs: runs given as frames + geometry JSON get no SR, with a warning
(:func:`write_qca_sr` returns why). The SR's own UIDs are derived from the source UIDs and the measured
values, so the same inputs give the same UIDs.

Reads: the source DICOM headers (no pixel data), qca.json's content and ``graphs_<key>.json`` (which frame of
each run the analysed key frame is). Writes: ``qca_sr.dcm`` (atomic).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..core.artefacts import atomic_path

log = logging.getLogger(__name__)

SR_NAME = "qca_sr.dcm"
LOCAL_SCHEME = "99AUTOCAR"

__all__ = ["write_qca_sr", "sr_sources", "SR_NAME", "CODES", "ARTERY_CODES"]


def _code(value: str, scheme: str, meaning: str):
    from pydicom.sr.coding import Code

    return Code(value, scheme, meaning)


# name -> (value, scheme, meaning); standard concepts from DICOM PS3.16 (DCM) and SNOMED CT (SCT)
CODES = {
    "procedure": ("33367005", "SCT", "Coronary angiography"),
    "coronary_artery": ("41801008", "SCT", "Coronary artery"),
    "stenosis": ("415582006", "SCT", "Stenosis"),
    "length": ("410668003", "SCT", "Length"),
    "lumen_diameter": ("397413000", "SCT", "Vessel lumen diameter"),
    "mean": ("373098007", "SCT", "Mean"),
    "minimum": ("255605001", "SCT", "Minimum"),
    "diameter_stenosis": ("408715008", "SCT", "Lumen Diameter Stenosis"),
    "lesion_length": ("408716009", "SCT", "Stenotic Lesion Length"),
    "distance": ("121206", "DCM", "Distance"),
    "algorithm": ("111001", "DCM", "Algorithm Name"),
    # no standard concept: the interpolated healthy diameter at the lesion, and where along the vessel it sits
    "reference_diameter": ("REFDIAM", LOCAL_SCHEME, "Reference lumen diameter"),
    "from_origin": ("FROMORIGIN", LOCAL_SCHEME, "Distance from the vessel origin along its centreline"),
}

# vessel name (stages.qca.labels) -> SNOMED CT body structure; segment-specific codes where they exist.
# D and OM are numbered in SNOMED CT (first, second, … diagonal) and QCA does not number them: they take the
# plain coronary artery code, the vessel's name staying in the group's tracking identifier.
ARTERY_CODES = {
    "LM": ("3227004", "Left main coronary artery"),
    "LAD": ("59438005", "Left anterior descending coronary artery"),
    "LCX": ("57396003", "Circumflex coronary artery"),
    "RCA": ("13647002", "Right coronary artery"),
    "AM": ("22765000", "Marginal branch of right coronary artery"),
    "proximal LAD": ("68787002", "Proximal left anterior descending coronary artery"),
    "mid LAD": ("91748002", "Mid left anterior descending coronary artery"),
    "distal LAD": ("36672000", "Distal left anterior descending coronary artery"),
    "proximal LCX": ("52433000", "Proximal circumflex coronary artery"),
    "mid LCX": ("91753007", "Mid circumflex coronary artery"),
    "distal LCX": ("6511003", "Distal circumflex coronary artery"),
    "proximal RCA": ("91083009", "Proximal right coronary artery"),
    "mid RCA": ("450960006", "Mid right coronary artery"),
    "distal RCA": ("41879009", "Distal right coronary artery"),
}


def _c(name: str):
    return _code(*CODES[name])


def _site(name: str):
    import highdicom as hd

    value, meaning = ARTERY_CODES.get(name, (CODES["coronary_artery"][0], CODES["coronary_artery"][2]))
    return hd.sr.FindingSite(_code(value, "SCT", meaning))


def sr_sources(recon) -> list[Path]:
    """The source runs of a reconstruction folder, as recorded in its predictions.zarr (paths as given to
    reconstruct, tried as they are and relative to the folder). Empty when unrecorded."""
    from ..core.artefacts import read_zarr
    from ..core.errors import UserError

    path = Path(recon) / "predictions.zarr"
    if not path.exists():
        return []
    try:
        inputs = list(dict(read_zarr(path, kind=None, schema_version=None).attrs).get("inputs") or [])
    except (UserError, OSError, ValueError, KeyError):
        return []
    out = []
    for p in inputs:
        p = Path(p)
        out.append(p if p.exists() or p.is_absolute() else Path(recon) / p)
    return out


def _headers(paths):
    """The DICOM headers of the source runs, or (None, why) when a run is not a readable DICOM file."""
    import pydicom

    out = []
    for p in paths:
        p = Path(p)
        if p.is_dir() or p.suffix.lower() in (".npy", ".npz", ".png", ".tif", ".tiff", ".jpg"):
            return None, f"{p.name} was read as image frames + geometry JSON: it has no DICOM UIDs to reference"
        try:
            ds = pydicom.dcmread(p, stop_before_pixels=True)
        except (OSError, pydicom.errors.InvalidDicomError) as exc:
            return None, f"{p}: not readable as DICOM ({exc})"
        missing = [k for k in ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID", "SOPClassUID") if not ds.get(k)]
        if missing:
            return None, f"{p.name}: no {', '.join(missing)} in its header"
        out.append(ds)
    return out, None


def _source_frames(recon: Path, key) -> dict:
    """Run name ('a', 'b') -> 0-based frame index of the analysed key frame, from graphs_<key>.json."""
    try:
        doc = json.loads((recon / f"graphs_{key}.json").read_text())
        views = doc["correspondences"]["views"]
        return {v: int(d["source_frame"]) for v, d in views.items() if d.get("source_frame") is not None}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def _measurement(name, value, unit, derivation=None, site=None):
    import highdicom as hd
    from pydicom.sr.codedict import codes

    units = {"mm": codes.UCUM.Millimeter, "%": codes.UCUM.Percent}
    return hd.sr.Measurement(name=_c(name), value=float(value), unit=units[unit],
                             derivation=_c(derivation) if derivation else None,
                             finding_sites=[site] if site is not None else None)


def mean_diameter(vd: dict) -> float:
    """A vessel's mean lumen diameter (mm): the mean of its diameter profile (equal steps along the vessel)."""
    d = np.asarray(vd["profile"]["diameter_mm"], float)
    return float(np.nanmean(d)) if len(d) else float("nan")


def write_qca_sr(recon, doc: dict, sources=None) -> dict:
    """Write ``qca_sr.dcm`` in ``recon`` for a QCA result ``doc`` (qca.json's content). ``sources``: the two
    runs' files (default: :func:`sr_sources`: run A, B and any further run). Returns ``{"file": "qca_sr.dcm"}`` or, when no SR can be
    written, ``{"file": None, "reason": ...}`` (the reason is logged as a warning). A stale SR is removed."""
    import highdicom as hd
    from pydicom.uid import generate_uid

    from .. import __version__

    recon = Path(recon)
    out = recon / SR_NAME
    sources = list(sources) if sources is not None else sr_sources(recon)
    reason = None
    if len(sources) < 2:
        reason = "the source runs are not recorded in predictions.zarr"
    elif not doc.get("vessels"):
        reason = doc.get("message") or "no vessel measured"
    headers = None
    if reason is None:
        headers, reason = _headers(sources)
    if reason is not None:
        out.unlink(missing_ok=True)
        msg = f"no DICOM SR written: {reason}"
        log.warning("%s", msg)
        return {"file": None, "reason": msg}

    frames = _source_frames(recon, doc.get("frame"))
    source_images = []
    for view, ds in zip("abcdefghijklmnopqrstuvwxyz", headers):  # run A, B (and every further run)
        n_frames = int(ds.get("NumberOfFrames", 1) or 1)
        ref = [frames[view] + 1] if view in frames and n_frames > 1 else None  # DICOM frame numbers are 1-based
        # built from the UIDs: from_source_image() would load the standard's attribute tables (0.3 s) to check
        # that the run is multi-frame, which NumberOfFrames already says
        source_images.append(hd.sr.SourceImageForMeasurementGroup(ds.SOPClassUID, ds.SOPInstanceUID,
                                                                  referenced_frame_numbers=ref))
    # the SR's UIDs follow from what it says: the same runs and figures give the same UIDs
    entropy = [ds.SOPInstanceUID for ds in headers] + [json.dumps(doc.get("vessels"), sort_keys=True, default=str)]
    algorithm = hd.sr.AlgorithmIdentification(name="AutoCAR 3D QCA", version=__version__)
    groups = []
    for vd in doc["vessels"]:
        site = _site(vd["name"])
        vessel_uid = generate_uid(entropy_srcs=entropy + [vd["id"]])
        groups.append(hd.sr.MeasurementsAndQualitativeEvaluations(
            tracking_identifier=hd.sr.TrackingIdentifier(uid=vessel_uid, identifier=f"{vd['name']} ({vd['id']})"),
            finding_type=_c("coronary_artery"), finding_sites=[site], algorithm_id=algorithm,
            source_images=source_images,
            measurements=[_measurement("length", vd["length_mm"], "mm"),
                          _measurement("lumen_diameter", mean_diameter(vd), "mm", "mean"),
                          _measurement("lumen_diameter", vd["min_diameter_mm"], "mm", "minimum")]))
        for les in vd["lesions"]:
            les_site = _site(les.get("segment") or vd["name"]) if (les.get("segment") or "") in ARTERY_CODES else site
            groups.append(hd.sr.MeasurementsAndQualitativeEvaluations(
                tracking_identifier=hd.sr.TrackingIdentifier(uid=generate_uid(entropy_srcs=entropy + [les["id"]]),
                                                             identifier=f"lesion {les['id']} in {vd['name']}"),
                finding_type=_c("stenosis"), finding_sites=[les_site], algorithm_id=algorithm,
                source_images=source_images,
                measurements=[_measurement("diameter_stenosis", les["ds_percent"], "%"),
                              _measurement("lumen_diameter", les["mld_mm"], "mm", "minimum"),
                              _measurement("reference_diameter", les["reference_mm"], "mm"),
                              _measurement("lesion_length", les["length_mm"], "mm"),
                              _measurement("from_origin", les["position_mm"], "mm")]))
    observer = hd.sr.ObserverContext(
        observer_type=_code("121007", "DCM", "Device"),
        observer_identifying_attributes=hd.sr.DeviceObserverIdentifyingAttributes(
            uid=generate_uid(entropy_srcs=["autocar", __version__]), name="AutoCAR", manufacturer_name="AutoCAR"))
    report = hd.sr.MeasurementReport(observation_context=hd.sr.ObservationContext(observer_device_context=observer),
                                     procedure_reported=_c("procedure"), imaging_measurements=groups)
    sr = _document(headers, report, entropy)
    with atomic_path(out) as tmp:
        sr.save_as(tmp, enforce_file_format=True)
    return {"file": SR_NAME}


COMPREHENSIVE_3D_SR = "1.2.840.10008.5.1.4.1.1.88.34"
# copied from run A: the SR belongs to its patient and study
PATIENT_STUDY = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyInstanceUID", "StudyDate",
                 "StudyTime", "ReferringPhysicianName", "StudyID", "AccessionNumber")


def _evidence(headers):
    """Per study the referenced series and instances (Hierarchical SOP Instance Reference Macro)."""
    from pydicom.dataset import Dataset

    studies: dict = {}
    for ds in headers:
        series = studies.setdefault(str(ds.StudyInstanceUID), {}).setdefault(str(ds.SeriesInstanceUID), [])
        series.append((str(ds.SOPClassUID), str(ds.SOPInstanceUID)))
    items = {}
    for study, by_series in studies.items():
        item = Dataset()
        item.StudyInstanceUID = study
        item.ReferencedSeriesSequence = []
        for series, refs in by_series.items():
            si = Dataset()
            si.SeriesInstanceUID = series
            si.ReferencedSOPSequence = []
            for cls, inst in dict.fromkeys(refs):
                ri = Dataset()
                ri.ReferencedSOPClassUID = cls
                ri.ReferencedSOPInstanceUID = inst
                si.ReferencedSOPSequence.append(ri)
            item.ReferencedSeriesSequence.append(si)
        items[study] = item
    return items


def _document(headers, report, entropy):
    """The Comprehensive 3D SR instance around the measurement report's content. Built with pydicom, not
    highdicom's Comprehensive3DSR: that one parses the standard's attribute tables on first use (0.3 s a run)."""
    import datetime

    from pydicom.dataset import Dataset
    from pydicom.uid import generate_uid

    now = datetime.datetime.now()
    sr = Dataset()
    sr.SpecificCharacterSet = "ISO_IR 192"
    sr.SOPClassUID = COMPREHENSIVE_3D_SR
    sr.SOPInstanceUID = generate_uid(entropy_srcs=entropy + ["sr"])
    for key in PATIENT_STUDY:
        setattr(sr, key, headers[0].get(key, ""))
    sr.Modality = "SR"
    sr.SeriesInstanceUID = generate_uid(entropy_srcs=entropy + ["series"])
    sr.SeriesNumber = 9051
    sr.SeriesDescription = "AutoCAR 3D QCA"
    sr.ReferencedPerformedProcedureStepSequence = []
    sr.Manufacturer = "AutoCAR"
    sr.InstanceNumber = 1
    sr.ContentDate = now.strftime("%Y%m%d")
    sr.ContentTime = now.strftime("%H%M%S")
    sr.InstanceCreationDate, sr.InstanceCreationTime = sr.ContentDate, sr.ContentTime
    sr.CompletionFlag = "COMPLETE"
    sr.VerificationFlag = "UNVERIFIED"
    evidence = _evidence(headers)
    own = str(sr.StudyInstanceUID)
    sr.CurrentRequestedProcedureEvidenceSequence = [evidence[own]] if own in evidence else []
    others = [item for study, item in evidence.items() if study != own]
    if others:
        sr.PertinentOtherEvidenceSequence = others
    sr.PerformedProcedureCodeSequence = []
    root = report[0]  # the TID 1500 container: the document's content
    for element in root:
        sr.add(element)
    sr.file_meta = Dataset()
    sr.file_meta.MediaStorageSOPClassUID = sr.SOPClassUID
    sr.file_meta.MediaStorageSOPInstanceUID = sr.SOPInstanceUID
    sr.file_meta.TransferSyntaxUID = "1.2.840.10008.1.2.1"  # explicit VR little endian
    return sr

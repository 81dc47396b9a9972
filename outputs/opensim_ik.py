"""OpenSim scaling and inverse kinematics on the TRC export, with Pose2Sim's model and setups.

Needs the optional extra ``opensim`` (``pip install 'roomcap[opensim]'``). The setup folder holds
an OpenSim model (``*.osim``), a marker set ``Markers_<set>.xml`` and the setups
``Scaling_Setup_Pose2Sim_<set>.xml`` and ``IK_Setup_Pose2Sim_<set>.xml`` (Pose2Sim's, BSD-3, in
``<shared>/data/opensim-pose2sim`` by default; ``--setup DIR`` for a lab's own).

Per person: the TRC (:func:`roomcap.outputs.export.write_trc`), the marker set added to the generic model,
scaling (the setup's measurements averaged over the whole trial; the markers placed on the
slowest quarter second), then inverse kinematics over the whole TRC, writing

- ``<session>_<id>.mot`` joint angles,
- ``<session>_<id>_marker_errors.csv``: per frame ``time_s, rms_m, max_m`` (OpenSim's own
  ``marker_error_RMS`` / ``marker_error_max`` over the markers that took part) and the error of
  each marker (model marker against the TRC, metres),
- ``<session>_<id>_scaled.osim``.

Markers the setups name that the TRC lacks are left out of scaling (a measurement that needs one is
not applied) and of IK, and named in the result's notes; fewer than 6 markers left is an error. A
body19 track's ``Neck`` (the mid-shoulder point) is left out, with a note, when the setup's ``Neck`` is an
upper-neck point (BODY_25B, HALPE-26: above the shoulder markers; :func:`neck_mismatch`).
"""

from __future__ import annotations

import logging
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from roomcap.core.errors import RoomcapError
from roomcap.core.fileio import atomic_write_text
from roomcap.outputs.export import marker_table, write_trc
from roomcap.track.trackfile import TrackFile, read_trc

log = logging.getLogger(__name__)

MIN_MARKERS = 6


class OpenSimError(RoomcapError, ValueError):
    """OpenSim is missing, the setup folder is incomplete, or too few markers; says what to do."""


@dataclass
class OpenSimResult:
    track_id: int | str
    trc: Path
    model: Path
    mot: Path
    errors_csv: Path
    markers: list[str]
    missing: list[str]
    time_s: np.ndarray
    rms_m: np.ndarray  # (T,)
    max_m: np.ndarray  # (T,)
    per_marker_m: np.ndarray  # (T,M)
    notes: list[str] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.time_s)

    @property
    def rms_median_m(self) -> float:
        return float(np.median(self.rms_m))

    @property
    def max_median_m(self) -> float:
        return float(np.median(self.max_m))


def default_setup_dir() -> Path:
    shared = Path(os.environ.get("ROOMCAP_SHARED", Path(__file__).resolve().parents[2] / "shared"))
    return shared / "data" / "opensim-pose2sim"


@dataclass(frozen=True)
class Setup:
    model: Path
    markers: Path
    scaling: Path
    ik: Path


def find_setup(setup_dir: Path, markerset: str) -> Setup:
    setup_dir = Path(setup_dir)
    if not setup_dir.is_dir():
        raise OpenSimError(
            f"OpenSim setup folder {setup_dir} not found; pass --setup DIR or set ROOMCAP_SHARED to the "
            "shared/ folder that holds data/opensim-pose2sim."
        )
    files = {p.name.lower(): p for p in setup_dir.iterdir()}
    ms = markerset.lower()

    def pick(name: str) -> Path:
        if name.lower() in files:
            return files[name.lower()]
        have = sorted(p.name for p in setup_dir.glob("*.xml"))
        raise OpenSimError(f"{setup_dir} has no {name} (it has {have}); choose another --markerset.")

    models = sorted(setup_dir.glob("*.osim"))
    if not models:
        raise OpenSimError(f"{setup_dir} has no OpenSim model (*.osim).")
    model = next((m for m in models if ms in m.name.lower()), models[0])
    return Setup(
        model,
        pick(f"Markers_{markerset}.xml"),
        pick(f"Scaling_Setup_Pose2Sim_{markerset}.xml"),
        pick(f"IK_Setup_Pose2Sim_{markerset}.xml"),
    )


def setup_marker_names(setup: Setup) -> list[str]:
    """Markers the IK setup gives a task to (applied)."""
    root = ET.parse(setup.ik).getroot()
    out = []
    for t in root.iter("IKMarkerTask"):
        apply = (t.findtext("apply") or "true").strip().lower() == "true"
        if apply:
            out.append(t.get("name"))
    return out


def marker_locations(setup: Setup) -> dict[str, tuple[str, np.ndarray]]:
    """Marker name -> (parent body, location in that body's frame, metres) of the setup's marker set."""
    out = {}
    for m in ET.parse(setup.markers).getroot().iter("Marker"):
        body = (m.findtext("socket_parent_frame") or "").strip().rsplit("/", 1)[-1]
        loc = np.array([float(v) for v in (m.findtext("location") or "0 0 0").split()])
        out[str(m.get("name"))] = (body, loc)
    return out


# a setup's Neck this far above its shoulder markers (torso frame) is an upper-neck keypoint (BODY_25B,
# HALPE-26), not the mid-shoulder point (Pose2Sim's COCO-17 set, at shoulder height)
UPPER_NECK_ABOVE_SHOULDERS_M = 0.03


def neck_mismatch(tf: TrackFile, setup: Setup) -> str | None:
    """Why the track's ``Neck`` must not take part, or None: body19's ``neck`` is the mid-shoulder point;
    a marker set whose ``Neck`` sits above its shoulder markers means the upper neck (BODY_25B's
    detected keypoint). Tracks with ``upper_neck`` export that as ``Neck`` and match."""
    if "upper_neck" in tf.joint_names or "neck" not in tf.joint_names:
        return None
    locs = marker_locations(setup)
    if "Neck" not in locs or "LShoulder" not in locs or "RShoulder" not in locs:
        return None
    (nb, neck), (lb, ls), (rb, rs) = locs["Neck"], locs["LShoulder"], locs["RShoulder"]
    if not nb == lb == rb:
        return None
    above = float(neck[1] - 0.5 * (ls[1] + rs[1]))
    if above <= UPPER_NECK_ABOVE_SHOULDERS_M:
        return None
    return (
        f"Neck left out: the setup's Neck ({setup.markers.name}) is an upper-neck point "
        f"{1000 * above:.0f} mm above its shoulder markers, the track's neck the mid-shoulder point "
        "(body19; the 2D model has no neck keypoint); use a track with the upper neck (BODY_25B, "
        "skeleton = whole_body) or a setup whose Neck is the mid-shoulder point (--markerset Coco17)"
    )


def foot_index_note(tf: TrackFile, setup: Setup) -> str | None:
    """A note when a BlazePose track (``foot_index``, exported as Pose2Sim names it: ``LBigToe``/``RBigToe``)
    meets a marker set whose ``LBigToe`` is another point (the BODY_25B big toe), or None."""
    if "left_big_toe" in tf.joint_names or "left_foot_index" not in tf.joint_names:
        return None
    if "blazepose" in setup.markers.name.lower():
        return None
    other = next(iter(sorted(setup.markers.parent.glob("Markers_[Bb]laze[Pp]ose.xml"))), None)
    where = ""
    if other is not None:
        here, there = (
            marker_locations(setup).get("LBigToe"),
            marker_locations(replace(setup, markers=other)).get("LBigToe"),
        )
        if here and there and here[0] == there[0]:
            where = f" ({1000 * float(np.linalg.norm(here[1] - there[1])):.0f} mm from {other.name}'s)"
    return (
        f"LBigToe/RBigToe are BlazePose's foot index (the foot tip); {setup.markers.name} places its "
        f"LBigToe on the big toe{where}: --markerset Blazepose matches BlazePose's points"
    )


def _import_opensim():
    try:
        import opensim as osim
    except ImportError:
        raise OpenSimError(
            "tracks opensim needs the opensim package: pip install 'roomcap[opensim]' "
            "(or: pip install opensim)."
        ) from None
    return osim


def _read_sto(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    i = next(i for i, ln in enumerate(lines) if ln.strip() == "endheader")
    cols = lines[i + 1].split("\t")
    data = np.array([[float(v) for v in ln.split()] for ln in lines[i + 2 :] if ln.strip()])
    return [c.strip() for c in cols], data.reshape(-1, len(cols))


def _slowest_window(xyz: np.ndarray, time_s: np.ndarray, width_s: float = 0.25) -> tuple[float, float]:
    """Time range of the ``width_s`` window where the markers move least (for placing markers)."""
    if len(time_s) < 3:
        return float(time_s[0]), float(time_s[-1])
    speed = np.linalg.norm(np.diff(xyz, axis=0), axis=-1).mean(-1)
    n = max(2, int(round(width_s / max(np.median(np.diff(time_s)), 1e-9))))
    n = min(n, len(speed))
    c = np.convolve(speed, np.ones(n), mode="valid")
    a = int(np.argmin(c))
    return float(time_s[a]), float(time_s[min(a + n, len(time_s) - 1)])


def run_opensim_trc(
    trc: Path,
    out_dir: Path,
    stem: str,
    setup_dir: Path,
    *,
    markerset: str = "Body25b",
    markers: list[str] | None = None,
    mass_kg: float | None = None,
    track_id: int | str = "",
) -> OpenSimResult:
    """Scale the model and run IK on one TRC (ours or Pose2Sim's); ``markers`` restricts the markers used."""
    osim = _import_opensim()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    setup = find_setup(setup_dir, markerset)
    names, xyz, time_s, _ = read_trc(trc)
    wanted = setup_marker_names(setup)
    missing = [m for m in wanted if m not in names]
    use = [m for m in wanted if m in names and (markers is None or m in markers)]
    notes = []
    if missing:
        notes.append(
            f"the setup {setup.ik.name} names markers the track lacks: {missing}; they are left out of "
            "scaling and inverse kinematics"
        )
    if len(use) < MIN_MARKERS:
        raise OpenSimError(
            f"only {len(use)} of the setup's markers are in {trc.name} ({use}); OpenSim needs at least "
            f"{MIN_MARKERS}. The setup names {wanted}; the TRC has {names}. Use the setup of the track's "
            "skeleton (--markerset) or a setup folder of your own (--setup)."
        )
    osim.Logger.setLevelString("error")
    osim.Logger.removeFileSink()
    osim.Logger.addFileSink(str(out_dir / "opensim.log"))
    generic = _generic_model(osim, setup, out_dir / f"{stem}_generic.osim")
    scaled = out_dir / f"{stem}_scaled.osim"
    t0, t1 = float(time_s[0]), float(time_s[-1])
    _scale(
        osim,
        setup,
        trc,
        generic,
        scaled,
        use,
        (t0, t1),
        _slowest_window(np.nan_to_num(xyz), time_s),
        mass_kg,
        notes,
    )
    mot = out_dir / f"{stem}.mot"
    _inverse_kinematics(osim, setup, trc, scaled, mot, stem, use, (t0, t1))
    t_err, rms, mx, per = _marker_errors(out_dir, stem, use, names, xyz, time_s)
    errors_csv = out_dir / f"{stem}_marker_errors.csv"
    head = "time_s,rms_m,max_m," + ",".join(f"{n}_m" for n in use)
    body = [
        f"{t:.6f},{r:.6f},{x:.6f}," + ",".join(f"{v:.6f}" for v in pm)
        for t, r, x, pm in zip(t_err, rms, mx, per, strict=True)
    ]
    atomic_write_text(errors_csv, "\n".join([head, *body]) + "\n")
    return OpenSimResult(track_id, trc, scaled, mot, errors_csv, use, missing, t_err, rms, mx, per, notes)


def _time_range(osim, a: float, b: float):
    tr = osim.ArrayDouble()
    tr.append(a)
    tr.append(b)
    return tr


def _generic_model(osim, setup, path: Path) -> Path:
    """The setup's model with its marker set added, written to ``path``."""
    model = osim.Model(str(setup.model))
    mset = osim.MarkerSet(str(setup.markers))
    have = {model.getMarkerSet().get(i).getName() for i in range(model.getMarkerSet().getSize())}
    for i in range(mset.getSize()):
        if mset.get(i).getName() not in have:
            model.addMarker(mset.get(i).clone())
    model.finalizeConnections()
    model.initSystem()
    model.printToXML(str(path))
    return path


def _scale(osim, setup, trc, generic, scaled, use, span, window, mass_kg, notes: list[str]) -> None:
    """OpenSim's ScaleTool on ``trc`` (markers ``use``): measurements needing other markers are not
    applied (said in ``notes``); the markers are placed in the slowest ``window``."""
    st = osim.ScaleTool(str(setup.scaling))
    if mass_kg:
        st.setSubjectMass(float(mass_kg))
    st.getGenericModelMaker().setModelFileName(str(generic))
    ms_ = st.getModelScaler()
    mset_meas = ms_.getMeasurementSet()
    for i in range(mset_meas.getSize()):
        meas = mset_meas.get(i)
        pairs = meas.getMarkerPairSet()
        need = {pairs.get(p).getMarkerName(e) for p in range(pairs.getSize()) for e in (0, 1)}
        if not need <= set(use):
            meas.setApply(False)
            notes.append(
                f"scaling measurement '{meas.getName()}' not applied (needs {sorted(need - set(use))})"
            )
    tr = _time_range(osim, *span)
    ms_.setMarkerFileName(str(trc))
    ms_.setTimeRange(tr)
    ms_.setOutputModelFileName(str(scaled))
    mp = st.getMarkerPlacer()
    _restrict_tasks(mp.getIKTaskSet(), use)
    tr2 = _time_range(osim, *window)
    mp.setMarkerFileName(str(trc))
    mp.setTimeRange(tr2)
    mp.setOutputModelFileName(str(scaled))
    mp.setApply(True)
    st.setPathToSubject("")
    if not st.run():
        raise OpenSimError(f"OpenSim scaling failed on {trc}; see {scaled.parent / 'opensim.log'}.")


def _inverse_kinematics(osim, setup, trc, scaled, mot, stem: str, use, span) -> None:
    """OpenSim's InverseKinematicsTool on ``trc`` with the scaled model; writes ``mot`` and the marker
    locations and errors beside it."""
    ik = osim.InverseKinematicsTool(str(setup.ik))
    scaled_model = osim.Model(str(scaled))  # kept referenced: the tool does not own it
    ik.setModel(scaled_model)
    _restrict_tasks(ik.getIKTaskSet(), use)
    ik.setMarkerDataFileName(str(trc))
    ik.setStartTime(span[0])
    ik.setEndTime(span[1])
    ik.setOutputMotionFileName(str(mot))
    ik.setResultsDir(str(mot.parent))
    ik.set_report_marker_locations(True)
    ik.set_report_errors(True)
    ik.setName(stem)
    ok = ik.run()
    del ik, scaled_model
    if not ok:
        raise OpenSimError(f"OpenSim inverse kinematics failed on {trc}; see {mot.parent / 'opensim.log'}.")


def _marker_errors(out_dir: Path, stem: str, use, names, xyz, time_s):
    """IK's RMS and largest marker error per frame, and each marker's: the model's marker locations
    against the TRC's."""
    cols, err = _read_sto(out_dir / f"{stem}_ik_marker_errors.sto")
    t_err, rms, mx = err[:, 0], err[:, cols.index("marker_error_RMS")], err[:, cols.index("marker_error_max")]
    lcols, loc = _read_sto(out_dir / f"{stem}_ik_model_marker_locations.sto")
    rows = np.searchsorted(time_s, t_err - 1e-6)
    per = np.full((len(t_err), len(use)), np.nan)
    for m, name in enumerate(use):
        try:
            c = lcols.index(f"{name}_tx")
        except ValueError:
            continue
        model_xyz = loc[:, c : c + 3]
        per[:, m] = np.linalg.norm(model_xyz - xyz[rows, names.index(name)], axis=-1)
    return t_err, rms, mx, per


def _restrict_tasks(task_set, use: list[str]) -> None:
    for i in range(task_set.getSize()):
        t = task_set.get(i)
        if t.getConcreteClassName() == "IKMarkerTask" and t.getName() not in use:
            t.setApply(False)


def run_opensim(
    tf: TrackFile,
    out_dir: Path,
    session: str,
    setup_dir: Path,
    *,
    persons: list[int] | None = None,
    markerset: str = "Body25b",
    max_gap: int = 10,
    markers: list[str] | None = None,
    mass_kg: float | None = None,
) -> list[OpenSimResult]:
    """TRC export + scaling + IK for every person (or ``persons``) of a track file."""

    _import_opensim()
    setup = find_setup(setup_dir, markerset)
    why = neck_mismatch(tf, setup) if markers is None or "Neck" in markers else None
    if why is not None:
        markers = [m for m in (markers or setup_marker_names(setup)) if m != "Neck"]
    out_dir = Path(out_dir)
    ids = tf.track_id.tolist() if persons is None else persons
    results = []
    for p in ids:
        stem = f"{session}_{p}"
        trc = out_dir / f"{stem}.trc"
        out_dir.mkdir(parents=True, exist_ok=True)
        write_trc(tf, p, trc, marker_table(tf, p, max_gap=max_gap))
        results.append(
            run_opensim_trc(
                trc,
                out_dir,
                stem,
                setup_dir,
                markerset=markerset,
                markers=markers,
                mass_kg=mass_kg,
                track_id=p,
            )
        )
        if why is not None:
            results[-1].notes.insert(0, why)
        toe = foot_index_note(tf, setup)
        if toe is not None and "LBigToe" in results[-1].markers:
            results[-1].notes.append(toe)
    return results

"""The project folder: ``project.toml``, the one object that owns every path, and stage records.

A project folder looks like::

    site/
      project.toml            CRS, local origin, cameras, settings overrides
      images/reference/       oblique photos (EXIF/XMP)
      images/queries/<seq>/   wide (..._W) and zoom (..._Z) photos
      model/                  reference textured mesh + offset sidecar
      gcp_list.txt            ground control points (OpenDroneMap format)
      tiepoints.json          tie points (see gtkit.io.tiepoints)
      truth/                  only on sample sites; only evaluation reads it
      work/<stage>/           each stage's outputs + stage.json (the settings that made them)
      exports/                dsm.tif, ortho.tif, mesh/, coordinates
      reports/                gt_report.json, localization.json, tracking.json + readable reports

Stages never invent a path: they ask :class:`Paths`.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import resource
import time
import tomllib
from pathlib import Path
from typing import Any

import tomli_w

from .errors import GtkitError
from .geo import GeoFrame
from .io.atomic import write_json, write_text
from .io.poses import INTRINSICS, POSES

PROJECT_FILE = "project.toml"
IMAGE_EXT = (".jpg", ".jpeg", ".png", ".tif", ".tiff")   # what counts as a photo under images/ (lower case)


class Paths:
    """Every location inside a project folder."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    project_toml = property(lambda s: s.root / PROJECT_FILE)
    images = property(lambda s: s.root / "images")
    reference_images = property(lambda s: s.root / "images" / "reference")
    query_images = property(lambda s: s.root / "images" / "queries")
    model = property(lambda s: s.root / "model")
    gcp_list = property(lambda s: s.root / "gcp_list.txt")
    geo_txt = property(lambda s: s.root / "geo.txt")
    tiepoints = property(lambda s: s.root / "tiepoints.json")
    cameras = property(lambda s: s.root / "cameras.txt")  # intrinsics priors, one line per image
    truth = property(lambda s: s.root / "truth")
    work = property(lambda s: s.root / "work")
    exports = property(lambda s: s.root / "exports")
    reports = property(lambda s: s.root / "reports")
    review = property(lambda s: s.root / "review.json")  # annotators' accept/reject per image
    dsm = property(lambda s: s.root / "exports" / "dsm.tif")          # gtkit export dsm
    ortho = property(lambda s: s.root / "exports" / "ortho.tif")      # gtkit export ortho
    mesh_export = property(lambda s: s.root / "exports" / "mesh")     # gtkit export mesh
    coordinates = property(lambda s: s.root / "exports" / "coordinates")  # gtkit export coords
    detections = property(lambda s: s.root / "detections.csv")       # target detections (gtkit track input)
    rig = property(lambda s: s.root / "work" / "rig" / "rig.json")    # gtkit track calibrate
    tracks = property(lambda s: s.root / "exports" / "tracks.csv")   # gtkit track (+ tracks.geojson)
    tracking_report = property(lambda s: s.root / "reports" / "tracking.json")  # gtkit track evaluate

    def stage(self, name: str) -> Path:
        return self.work / name

    # Pose sets (gtkit.io.poses formats): a stage's, and the ones every reader asks for by name.
    def poses(self, stage: str) -> Path:
        return self.stage(stage) / POSES

    def intrinsics(self, stage: str) -> Path:
        return self.stage(stage) / INTRINSICS

    reference_poses = property(lambda s: s.poses("sfm_reference"))     # the reference block's SfM
    reference_intrinsics = property(lambda s: s.intrinsics("sfm_reference"))
    pseudo_gt_poses = property(lambda s: s.poses("register"))          # gtkit register's query poses
    localized_poses = property(lambda s: s.poses("localize"))          # gtkit localize's
    registration = property(lambda s: s.stage("register") / "registration.json")  # its record
    truth_poses = property(lambda s: s.truth / POSES)                  # a sample's truth (evaluation only)
    truth_intrinsics = property(lambda s: s.truth / INTRINSICS)

    def query_sequences(self) -> list[str]:
        if not self.query_images.is_dir():
            return []
        return sorted(p.name for p in self.query_images.iterdir() if p.is_dir())


@dataclasses.dataclass
class Project:
    """A loaded ``project.toml``."""

    paths: Paths
    frame: GeoFrame
    name: str = "site"
    config: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def load(cls, root: str | Path) -> "Project":
        paths = Paths(root)
        f = paths.project_toml
        if not f.is_file():
            raise GtkitError(f"not a gtkit project ({PROJECT_FILE} missing)", paths.root)
        try:
            cfg = tomllib.loads(f.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as e:
            raise GtkitError(f"invalid TOML ({e})", f) from None
        crs = cfg.get("crs", {})
        if "crs" not in crs:
            raise GtkitError("[crs] crs = 'EPSG:...' missing", f)
        origin = crs.get("origin", [0.0, 0.0, 0.0])
        frame = GeoFrame(str(crs["crs"]), tuple(float(v) for v in origin), source=str(f))
        return cls(paths, frame, cfg.get("project", {}).get("name", paths.root.name), cfg)

    @classmethod
    def create(cls, root: str | Path, frame: GeoFrame, name: str = "site", extra: dict | None = None) -> "Project":
        paths = Paths(root)
        paths.root.mkdir(parents=True, exist_ok=True)
        cfg = {"project": {"name": name, "gtkit_version": _version()},
               "crs": {"crs": frame.crs_spec, "origin": list(frame.origin),
                       "note": "world = CRS coordinates minus origin; metres; z up; heights as given"}}
        cfg.update(extra or {})
        proj = cls(paths, frame, name, cfg)
        proj.save()
        return proj

    def save(self) -> None:
        write_text(self.paths.project_toml, tomli_w.dumps(self.config))

    def section(self, name: str) -> dict:
        return self.config.get(name, {})

    def record_import(self, kind: str, source: str | Path, **info) -> None:
        """Remember in project.toml what was imported and from where. ``source`` is kept as given
        (an outside file); paths of what was written into the project are stored relative to it."""
        imports = self.config.setdefault("imports", {})
        imports[kind] = {"source": str(source), "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
                         **relative_paths(info, self.paths.root)}
        self.save()


def _version() -> str:
    from . import __version__

    return __version__


# --- stage records: resume when the settings match, recompute when they changed ------------

STAGE_RECORD = "stage.json"


@dataclasses.dataclass
class StageRecord:
    """A finished stage's record (``work/<stage>/stage.json``), as :func:`mark_stage_done` wrote it."""
    path: Path
    settings: dict
    inputs: dict
    summary: dict
    finished: str = ""
    key: str = ""


def read_stage_record(stage_dir: str | Path) -> StageRecord | None:
    """The record in ``stage_dir``; None when the stage has not finished there (no record, or one
    that is not a record: a half-written file is never taken for a finished stage)."""
    f = Path(stage_dir) / STAGE_RECORD
    try:
        data = json.loads(f.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if not isinstance(data, dict):
        return None
    return StageRecord(f, data.get("settings") or {}, data.get("inputs") or {}, data.get("summary") or {},
                       data.get("finished", ""), data.get("key", ""))


def settings_dict(settings: Any) -> dict:
    if dataclasses.is_dataclass(settings):
        return json.loads(json.dumps(dataclasses.asdict(settings), default=str))
    return json.loads(json.dumps(settings or {}, default=str))


def settings_key(settings: Any) -> str:
    blob = json.dumps(settings_dict(settings), sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def stage_done(stage_dir: Path, settings: Any, inputs: dict | None = None) -> bool:
    """True when ``stage_dir`` holds a finished run made with these settings (and inputs).
    Paths inside the project are compared relative to its root, so a copied or moved project
    resumes; a record written before that (absolute paths) still counts where it was made."""
    rec = Path(stage_dir) / STAGE_RECORD
    if not rec.is_file():
        start_stage_clock(stage_dir)
        return False
    try:
        data = json.loads(rec.read_text())
    except json.JSONDecodeError:
        start_stage_clock(stage_dir)
        return False
    root = find_root(stage_dir)
    raw = {"settings": settings_dict(settings), "inputs": inputs or {}}
    if data.get("key") in (settings_key(relative_paths(raw, root)), settings_key(raw)):
        return True
    start_stage_clock(stage_dir)
    return False


def mark_stage_done(stage_dir: Path, settings: Any, inputs: dict | None = None, *,
                    outputs: list[Path] | None = None, **summary) -> None:
    """Write the record that makes a later run with the same settings skip this stage.
    Call it last, after every output is written. Paths inside the project are stored relative to
    its root (see :func:`relative_paths`). When the stage's clock runs (started by
    :func:`stage_done` finding no matching record, or by :func:`start_stage_clock`) the summary
    gets ``cost``: wall and CPU seconds, peak memory, disk of ``stage_dir`` + ``outputs``."""
    clock = _CLOCKS.pop(_clock_key(stage_dir), None)
    if clock is not None and "cost" not in summary:
        summary["cost"] = clock.cost([Path(stage_dir), *(outputs or [])])
    root = find_root(stage_dir)
    rec = relative_paths({"settings": settings_dict(settings), "inputs": inputs or {}}, root)
    write_json(Path(stage_dir) / STAGE_RECORD, {
        "key": settings_key(rec), **rec,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"), "summary": relative_paths(summary, root)})


# --- what a stage cost: wall, CPU, peak memory, disk ------------------------------------------

def cpu_seconds() -> float:
    """CPU seconds of this process and its reaped children so far (user + system)."""
    return sum(_cpu_seconds())


def _cpu_seconds() -> tuple[float, float]:
    me, ch = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime, ch.ru_utime + ch.ru_stime


def _peak_rss_bytes() -> int | None:
    """This process's peak resident set (VmHWM) since start or since the last reset."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _reset_peak_rss() -> bool:
    """Reset VmHWM to the current RSS (Linux: ``5`` into /proc/self/clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def disk_bytes(*paths: Path) -> int:
    """Bytes of the files under ``paths`` (apparent size, links not followed)."""
    total = 0
    for p in map(Path, paths):
        if p.is_file() and not p.is_symlink():
            total += p.stat().st_size
        elif p.is_dir():
            for dirpath, _dirs, files in os.walk(p):
                for f in files:
                    try:
                        st = os.lstat(os.path.join(dirpath, f))
                    except OSError:
                        continue
                    total += st.st_size
    return total


class StageClock:
    """Wall and CPU seconds (this process + its reaped children) from now, peak RSS of this process
    from now (VmHWM, reset at start; stages nested in one process fold their peaks into the outer
    clock), the largest reaped child's peak RSS if a child finished meanwhile (Linux counts a
    child's pages from before its exec: a lower bound of it is the parent's RSS at the fork), and
    the 1-minute load average at start and end (wall seconds at a high load are upper bounds)."""

    def __init__(self):
        _fold_peaks()
        self.t0 = time.time()
        self.cpu0 = _cpu_seconds()
        self.child_peak0 = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        self.load0 = os.getloadavg()[0]
        self.peak = 0
        self.scope = "stage" if _reset_peak_rss() else "process"

    def cost(self, outputs: list[Path]) -> dict:
        _fold_peaks()
        self.peak = max(self.peak, _peak_rss_bytes() or 0)
        me, ch = _cpu_seconds()
        child_peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # kB on Linux
        cpu_me, cpu_ch = me - self.cpu0[0], ch - self.cpu0[1]
        return {"wall_s": round(time.time() - self.t0, 2), "cpu_s": round(cpu_me + cpu_ch, 2),
                "cpu_children_s": round(cpu_ch, 2), "peak_rss_gb": round(self.peak / 2**30, 3),
                "peak_rss_scope": self.scope,
                "children_peak_rss_gb": round(child_peak / 2**20, 3)
                if cpu_ch > 0 and child_peak > self.child_peak0 else None,
                "disk_mb": round(disk_bytes(*outputs) / 2**20, 2),
                "load_avg_1m": [round(self.load0, 2), round(os.getloadavg()[0], 2)]}


_CLOCKS: dict[str, StageClock] = {}


def _clock_key(stage_dir: Path) -> str:
    return str(Path(stage_dir).absolute())


def _fold_peaks() -> None:
    """Every running clock takes the peak so far, before a reset would lose it."""
    peak = _peak_rss_bytes() or 0
    for c in _CLOCKS.values():
        c.peak = max(c.peak, peak)


def reset_peak_rss() -> None:
    """Start a new peak-memory window for a step inside a stage (Linux: VmHWM reset); every running
    stage clock keeps the peak so far. Use this, never a bare clear_refs write."""
    _fold_peaks()
    _reset_peak_rss()


def start_stage_clock(stage_dir: Path) -> StageClock:
    """Start (or restart) measuring the stage that writes ``stage_dir``; read by :func:`mark_stage_done`."""
    from .logs import stage_started

    stage_started(stage_dir)  # under quiet_terminal: the C libraries' output goes to work/<stage>/log.txt
    clock = StageClock()
    _CLOCKS[_clock_key(stage_dir)] = clock
    _fold_peaks()
    return clock


# --- portable projects: paths inside the project are stored relative to its root ---------------

def find_root(path: str | Path) -> Path | None:
    """The project folder holding ``path`` (the nearest parent with a project.toml), or None."""
    p = Path(path)
    for d in (p, *p.parents):
        if (d / PROJECT_FILE).is_file():
            return d
    return None


def relative_paths(obj: Any, root: str | Path | None) -> Any:
    """``obj`` (JSON-like) with every string that is a path inside ``root`` (as given, or resolved)
    made relative to it, in dict keys too. Paths outside the project (import sources) stay absolute."""
    if root is None:
        return obj
    root = Path(root)
    prefixes = sorted({str(root), str(root.resolve()), str(root.absolute())}, key=len, reverse=True)

    def rel(s: str) -> str:
        for pre in prefixes:
            if s == pre:
                return "."
            if s.startswith(pre.rstrip("/") + "/"):
                return s[len(pre.rstrip("/")) + 1:]
        return s

    if isinstance(obj, str):
        return rel(obj)
    if isinstance(obj, dict):
        return {(rel(k) if isinstance(k, str) else k): relative_paths(v, root) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [relative_paths(v, root) for v in obj]
    return obj


def resolve_path(p: str | Path, root: str | Path) -> Path:
    """A path read from a project file: relative ones are under ``root``; an absolute one that no
    longer exists (a project copied or moved before paths were stored relative) is looked up under
    ``root`` by its trailing components (``/old/site/work/register/poses.txt`` -> ``work/register/poses.txt``)."""
    p, root = Path(p), Path(root)
    if not p.is_absolute():
        return root / p
    if p.exists():
        return p
    parts = p.parts[1:]
    for k in range(len(parts)):
        cand = root.joinpath(*parts[k:])
        if cand.exists():
            return cand
    return p


def clear_stage(stage_dir: Path) -> None:
    (Path(stage_dir) / STAGE_RECORD).unlink(missing_ok=True)


def file_fingerprint(path: Path) -> str:
    """A cheap identity of an input file (size + mtime + sha of the first MiB)."""
    path = Path(path)
    if not path.exists():
        return "missing"
    st = path.stat()
    with open(path, "rb") as f:
        head = hashlib.sha256(f.read(1 << 20)).hexdigest()[:12]
    return f"{st.st_size}-{head}"

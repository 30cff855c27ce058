"""Settings of the sample generator; presets are readable TOML files in ``sample_projects/``.

Every field has a documented default; a preset file overrides fields section by section
(``[site]``, ``[world]``, ``[reference]``, ``[queries]``, ``[[queries.sequences]]``, ``[model]``,
``[annotation]``, ``[targets]``). Unknown keys are errors, so a typo never goes unnoticed.
"""
from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import GtkitError

PRESET_DIR = Path(__file__).resolve().parents[2] / "sample_projects"


@dataclass
class SiteSettings:
    lat: float = 30.52             # site centre, WGS84 degrees (a site near Wuhan -> UTM 50N)
    lon: float = 114.31
    base_height: float = 22.0      # terrain height at the centre (metres, heights as in the CRS)
    size_m: float = 250.0          # the site is a size_m x size_m square around the centre
    terrain_spacing_m: float = 2.0  # true terrain grid spacing
    relief_m: float = 4.0          # amplitude of the gentle terrain relief


@dataclass
class WorldSettings:
    block_m: float = 60.0          # town block size (between road centre lines)
    town_share: float = 0.45       # eastern share of the site that is town (rest: rural + lake)
    building_height_min: float = 5.0
    building_height_max: float = 80.0
    tower_share: float = 0.15      # share of buildings that are towers (25 m .. max height)
    gabled_share: float = 0.45     # share of low buildings with gabled roofs
    n_farm_houses: int = 4         # gabled houses in the rural part
    tree_density: float = 0.0025   # trees per square metre of rural land (plus street trees)
    lake: bool = True
    n_gcps: int = 6                # ground control targets (marked squares)
    gcp_size_m: float = 1.6


@dataclass
class ReferenceSettings:
    width: int = 1024
    height: int = 768
    hfov_deg: float = 73.7
    altitude_agl: float = 120.0    # flight height above the site centre
    overlap_forward: float = 0.75  # nadir image overlap along a strip
    overlap_side: float = 0.70     # nadir image overlap between strips
    oblique_pitch_deg: float = -45.0
    coverage_share: float = 0.62   # the flight grid covers this share of the site side
    gps_sigma_m: float = 0.025     # RTK
    angle_sigma_deg: float = 0.3
    sun_azimuth_deg: float = 150.0
    sun_elevation_deg: float = 60.0
    ambient: float = 0.6
    gain: float = 1.05
    noise_sigma: float = 1.5       # sensor noise, DN (0..255)
    blur_sigma_px: float = 0.4
    jpeg_quality: int = 92
    date: str = "2026-05-12T10:00:00"   # simulated time of the first photo
    seconds_per_station: float = 3.0


@dataclass
class SequenceSettings:
    name: str = "seq1"
    follow: str = "car"            # car | person | area (random ground points)
    height_agl: float = 100.0      # flight height above the followed point
    pitch_deg: float = -45.0       # gimbal pitch (15..70 deg below the horizon)
    n_continuous: int = 8          # continuous shots ...
    interval_s: float = 2.0        # ... every interval_s seconds
    n_manual: int = 2              # random manual shots during the sequence
    start_s: float = 0.0           # start, seconds after [queries] date
    orbit_deg_per_s: float = 2.0   # how fast the drone circles the followed point


@dataclass
class QuerySettings:
    wide_width: int = 1024
    wide_height: int = 768
    wide_hfov_deg: float = 82.0
    wide_k1: float = -0.06         # radial distortion of the wide camera (RADIAL model; 0 = none)
    wide_k2: float = 0.015
    zoom_width: int = 640
    zoom_height: int = 480
    zoom_hfov_deg: float = 18.0
    zoom_rotation_deg: list = field(default_factory=lambda: [0.35, -0.25, 0.15])  # rotvec, zoom from wide
    zoom_offset_m: list = field(default_factory=lambda: [0.035, -0.02, 0.01])     # zoom from wide
    gps_sigma_m: float = 4.0       # consumer GPS
    alt_sigma_m: float = 1.5
    angle_sigma_deg: float = 1.5   # IMU / gimbal noise per angle
    roll_sigma_true_deg: float = 0.4
    aim_jitter_m: float = 3.0      # how far from the followed target the camera aims
    # A pilot keeps clear of what stands near the drone: a camera with a building top or tree top
    # within clearance_radius_m horizontally climbs to clearance_m above it (without it small seeds
    # 22, 27 and 33 flew a sequence through or beside a tower taller than its flight height).
    clearance_m: float = 10.0
    clearance_radius_m: float = 15.0
    sun_azimuth_deg: float = 250.0
    sun_elevation_deg: float = 30.0
    ambient: float = 0.5
    gain: float = 0.9
    gain_jitter: float = 0.06
    tint: list = field(default_factory=lambda: [1.06, 1.0, 0.9])
    noise_sigma: float = 3.0
    blur_sigma_px: float = 0.7
    jpeg_quality: int = 90
    date: str = "2026-05-14T16:30:00"
    sequences: list = field(default_factory=list)


@dataclass
class ModelSettings:
    terrain_spacing_m: float = 4.0  # the reference mesh's terrain is resampled (decimated)
    noise_m: float = 0.03          # geometric noise on every vertex
    texture_gsd_m: float = 0.08    # texture resolution
    tree_texture_gsd_m: float = 0.16
    atlas_size: int = 4096
    offset_round_m: float = 1000.0  # OBJ vertices = CRS minus this rounded offset


@dataclass
class AnnotationSettings:
    gcp_click_sigma_px: float = 0.5
    gcp_max_clicks: int = 8        # clicks per GCP (most central views)
    tie_sigma_px: float = 1.0
    tiepoints_wide: list = field(default_factory=lambda: [6, 12])   # min, max per wide photo
    tiepoints_zoom: list = field(default_factory=lambda: [3, 5])    # min, max per zoom photo
    refs_per_tiepoint: list = field(default_factory=lambda: [1, 3])  # reference clicks per point
    gross_share: float = 0.08      # share of tie points with one grossly wrong click
    gross_px: list = field(default_factory=lambda: [25.0, 80.0])


@dataclass
class TargetSettings:
    car_speed: float = 8.0         # m/s, drives a loop around a town block
    person_speed: float = 1.4      # m/s, walks back and forth in the rural part
    track_step_s: float = 0.5      # sampling of truth/targets.csv


@dataclass
class SynthSettings:
    preset: str = "custom"
    seed: int = 0
    gps_denied: bool = False
    site: SiteSettings = field(default_factory=SiteSettings)
    world: WorldSettings = field(default_factory=WorldSettings)
    reference: ReferenceSettings = field(default_factory=ReferenceSettings)
    queries: QuerySettings = field(default_factory=QuerySettings)
    model: ModelSettings = field(default_factory=ModelSettings)
    annotation: AnnotationSettings = field(default_factory=AnnotationSettings)
    targets: TargetSettings = field(default_factory=TargetSettings)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


_SECTIONS = {"site": SiteSettings, "world": WorldSettings, "reference": ReferenceSettings,
             "queries": QuerySettings, "model": ModelSettings, "annotation": AnnotationSettings,
             "targets": TargetSettings}


def _fill(cls, values: dict, where: str, source):
    names = {f.name for f in dataclasses.fields(cls)}
    bad = sorted(set(values) - names)
    if bad:
        raise GtkitError(f"[{where}]: unknown setting(s) {', '.join(bad)}", source)
    obj = cls()
    for k, v in values.items():
        default = getattr(obj, k)
        if isinstance(default, float) and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if default is not None and not isinstance(v, type(default)) and k != "sequences":
            raise GtkitError(f"[{where}] {k}: expected {type(default).__name__}, got {v!r}", source)
        setattr(obj, k, v)
    return obj


def settings_from_dict(d: dict, source=None) -> SynthSettings:
    s = SynthSettings()
    for k, v in d.items():
        if k in _SECTIONS:
            if not isinstance(v, dict):
                raise GtkitError(f"[{k}] must be a table", source)
            v = dict(v)
            seqs = v.pop("sequences", None) if k == "queries" else None
            obj = _fill(_SECTIONS[k], v, k, source)
            if k == "queries":
                obj.sequences = [_fill(SequenceSettings, dict(q), f"queries.sequences #{i + 1}", source)
                                 for i, q in enumerate(seqs or [])]
            setattr(s, k, obj)
        elif k in ("preset", "seed", "gps_denied"):
            setattr(s, k, v)
        else:
            raise GtkitError(f"unknown section or key {k!r}", source)
    if not s.queries.sequences:
        s.queries.sequences = [SequenceSettings()]
    names = [q.name for q in s.queries.sequences]
    if len(set(names)) != len(names):
        raise GtkitError(f"duplicate query sequence names {names}", source)
    for q in s.queries.sequences:
        if not -70.0 <= q.pitch_deg <= -15.0:
            raise GtkitError(f"sequence {q.name}: pitch_deg must be in [-70, -15]", source)
        if q.follow not in ("car", "person", "area"):
            raise GtkitError(f"sequence {q.name}: follow must be car, person or area", source)
    return s


def preset_path(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml":
        return p
    return PRESET_DIR / f"{name_or_path}.toml"


def load_preset(name_or_path: str, seed: int | None = None, gps_denied: bool | None = None) -> SynthSettings:
    """Settings from a preset name (``small``, ``medium``, ``large``, ...) or a TOML path."""
    path = preset_path(name_or_path)
    if not path.is_file():
        avail = sorted(q.stem for q in PRESET_DIR.glob("*.toml")) if PRESET_DIR.is_dir() else []
        raise GtkitError(f"no such preset (available: {', '.join(avail) or 'none'})", path)
    try:
        d = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise GtkitError(f"invalid TOML ({e})", path) from None
    d.setdefault("preset", path.stem)
    s = settings_from_dict(d, path)
    if seed is not None:
        s.seed = int(seed)
    if gps_denied is not None:
        s.gps_denied = bool(gps_denied)
    return s

"""Guided annotation: the tie-point clicks that would cut a query sequence's pose uncertainty most.

A first-order information gain on the registration's own bundle adjustment. The final joint BA
(:mod:`gtkit.sfm.register`) gives the covariance of every query photo's pose, cross terms between
the photos of one sequence included (``6N x 6N``, the BA's units: one pixel per observation, the
sigma of a simulated or careful click). A candidate tie point, clicked once in a query photo at
pixel ``u`` and in reference photos (fixed poses) at theirs, adds one new 3-D point and its
observations. With the point marginalised (Schur complement) its information on the photo's pose
is ``H = J^T W J`` with ``J`` the click's 2x6 Jacobian on the pose (left perturbation
``R' = exp(dr) R``, ``t' = t + dt``, as the covariance) and ``W = I - B M^-1 B^T``
(``B``: the click's Jacobian on the point; ``M``: the point's information from all its clicks):
a reference point fixed by two reference clicks gives ``W`` near the identity, one reference
click leaves the point free along its ray and ``W`` of rank one. The covariance after the click
is the rank-2 update ``S' = S - S E^T L (I + L^T S_kk L)^-1 L^T E S`` (``H = L L^T``), exact for
the linearised BA.

A sequence's sigma is the RMS over its photos of the position sigma ``sqrt(trace C)`` of each
camera centre, the BA's part plus the per-photo systematic part the register stage adds (which
clicks do not reduce). :func:`greedy` takes the candidate with the largest drop of the summed
``trace C``, updates the covariance, and repeats: the suggested clicks in order, each with the
sigma expected after it. Where every suggestion together would lower a sequence's sigma by less than
``min_useful_drop`` (a sequence held by its automatic ties), it is said so and the annotator is sent
elsewhere (``clicks_help``). The library writes what it finds (``work/register/guided_clicks.json``,
the GT report); the annotator (``gui/``) only shows it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..pose import Pose

GUIDANCE_FILE = "guided_clicks.json"
COVARIANCE_FILE = "sequence_covariance.npz"


@dataclass
class GuidanceSettings:
    """``[register.guidance]``: the next clicks suggested per sequence (``guided_clicks.json``)."""
    enabled: bool = True
    target_m: float = 0.05       # the sequence sigma (RMS over its photos) the suggestions aim at
    max_clicks: int = 10         # suggestions per sequence at most
    grid: list = field(default_factory=lambda: [4, 3])   # candidate cells per query photo (columns, rows)
    reference_views: int = 2     # reference photos a suggested point is to be clicked in
    click_sigma_px: float = 1.0  # assumed click noise, in the BA's units (1 px per observation)
    # a sequence whose suggested clicks, all of them, would lower its sigma by less than this share is
    # said to be held by its automatic ties beyond what clicks can add (small seeds 33-40: every one of
    # a sequence's 63-100 clicks lowered its sigma by 0.1-3.3 % with the automatic ties on)
    min_useful_drop: float = 0.05


@dataclass
class Candidate:
    """A tie point that could be clicked: in query ``photo`` at ``xy`` and in ``reference`` photos
    [(name, xy)], on the ground point ``xyz`` (reference frame). ``id``: a sample's tie point id."""
    photo: str
    xy: tuple[float, float]
    xyz: np.ndarray
    reference: list[tuple[str, tuple[float, float]]]
    id: str = ""


@dataclass
class SequenceState:
    """One registered sequence: its photos (joint-model order), their poses and cameras, the joint
    pose covariance ``cov`` (6N x 6N, BA units) and each photo's systematic centre variance
    (``floor``, m^2, trace of the part clicks do not reduce)."""
    seq: str
    names: list[str]
    poses: list[Pose]
    cams: list[Camera]
    cov: np.ndarray
    floor: np.ndarray

    def centre_jacobians(self) -> np.ndarray:
        return np.array([p.center_jacobian() for p in self.poses])     # (N, 3, 6)

    def photo_sigmas(self, cov: np.ndarray | None = None) -> np.ndarray:
        """Each photo's position sigma (m): sqrt(trace of its centre covariance) + its floor."""
        cov = self.cov if cov is None else cov
        Jc = self.centre_jacobians()
        out = []
        for k, J in enumerate(Jc):
            S = cov[6 * k:6 * k + 6, 6 * k:6 * k + 6]
            out.append(np.trace(J @ S @ J.T) + self.floor[k])
        return np.sqrt(np.maximum(out, 0.0))

    def sigma(self, cov: np.ndarray | None = None) -> float:
        """The sequence's sigma: RMS of its photos' position sigmas."""
        s = self.photo_sigmas(cov)
        return float(np.sqrt(np.mean(s ** 2))) if len(s) else float("nan")


def _pixel_jacobian(cam: Camera, Xc: np.ndarray, h: float = 1e-4) -> np.ndarray:
    """d(pixel)/d(camera-frame point), 2x3, central differences (distortion included)."""
    Xc = np.asarray(Xc, float)
    J = np.zeros((2, 3))
    for a in range(3):
        d = np.zeros(3)
        d[a] = h * max(1.0, abs(Xc[2]))
        J[:, a] = (cam.project((Xc + d)[None])[0][0] - cam.project((Xc - d)[None])[0][0]) / (2 * d[a])
    return J


def click_information(pose: Pose, cam: Camera, xyz: np.ndarray, ref_views: list[tuple[Pose, Camera]],
                      sigma_px: float = 1.0) -> np.ndarray:
    """6x2 ``L`` with ``L L^T`` the information one tie point (query click in a photo of ``pose``,
    clicks in the fixed ``ref_views``) adds on that photo's pose, its 3-D point marginalised."""
    Xc = pose.R @ xyz + pose.t
    P = _pixel_jacobian(cam, Xc)
    J = P @ pose.point_jacobian(xyz) / sigma_px                                   # 2x6
    B = P @ pose.R / sigma_px                                                      # 2x3
    M = B.T @ B
    for rp, rc in ref_views:
        A = _pixel_jacobian(rc, rp.R @ xyz + rp.t) @ rp.R / sigma_px
        M = M + A.T @ A
    W = np.eye(2) - B @ np.linalg.pinv(M) @ B.T
    w, V = np.linalg.eigh((W + W.T) / 2)
    return J.T @ (V * np.sqrt(np.clip(w, 0.0, None)))


def _update(cov: np.ndarray, k: int, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(U, S^-1) of the rank-2 update: cov' = cov - U S^-1 U^T."""
    U = cov[:, 6 * k:6 * k + 6] @ L
    S = np.eye(L.shape[1]) + L.T @ U[6 * k:6 * k + 6]
    return U, np.linalg.inv(S)


def with_click(cov: np.ndarray, k: int, L: np.ndarray) -> np.ndarray:
    """The covariance after one click (photo index ``k``, information ``L``)."""
    U, Si = _update(cov, k, L)
    return cov - U @ Si @ U.T


def trace_drop(state: SequenceState, k: int, L: np.ndarray, Jc: np.ndarray | None = None) -> float:
    """How much one click (photo index ``k``, information ``L``) lowers the summed centre variance."""
    Jc = state.centre_jacobians() if Jc is None else Jc
    U, Si = _update(state.cov, k, L)
    V = np.einsum("nij,njk->nik", Jc, U.reshape(-1, 6, L.shape[1]))      # (N, 3, 2)
    return float(np.einsum("nik,kl,nil->", V, Si, V))


def candidate_information(state: SequenceState, c: Candidate, ref_poses: dict[str, tuple[Pose, Camera]],
                          sigma_px: float = 1.0) -> tuple[int, np.ndarray] | None:
    """(photo index, L) of a candidate, None where its photo is not in the sequence's registration."""
    if c.photo not in state.names:
        return None
    k = state.names.index(c.photo)
    refs = [ref_poses[n] for n, _ in c.reference if n in ref_poses]
    return k, click_information(state.poses[k], state.cams[k], np.asarray(c.xyz, float), refs, sigma_px)


def greedy(state: SequenceState, candidates: list[Candidate], ref_poses: dict[str, tuple[Pose, Camera]],
           max_clicks: int, target_m: float | None = None, sigma_px: float = 1.0) -> list[tuple[Candidate, float]]:
    """The candidates in the order the guidance takes them, each with the sequence sigma expected
    after it; stops after ``max_clicks``, when the sigma reaches ``target_m`` or nothing helps."""
    st = SequenceState(state.seq, state.names, state.poses, state.cams, state.cov.copy(), state.floor)
    Jc = st.centre_jacobians()
    info = [(c, candidate_information(st, c, ref_poses, sigma_px)) for c in candidates]
    info = [(c, i) for c, i in info if i is not None]
    out = []
    while info and len(out) < max_clicks:
        if target_m is not None and st.sigma() <= target_m:
            break
        drops = [trace_drop(st, k, L, Jc) for _, (k, L) in info]
        b = int(np.argmax(drops))
        if drops[b] <= 0:
            break
        c, (k, L) = info.pop(b)
        st.cov = with_click(st.cov, k, L)
        out.append((c, st.sigma()))
    return out


def spread_start(candidates: list[Candidate], n: int = 3) -> list[Candidate]:
    """Before a sequence is registered there is no covariance: ``n`` candidates in different photos
    whose ground points lie farthest apart (farthest-point order from the first photo's)."""
    if not candidates:
        return []
    picked = [candidates[0]]
    while len(picked) < n:
        used = {c.photo for c in picked}
        rest = [c for c in candidates if c.photo not in used] or [c for c in candidates if c not in picked]
        if not rest:
            break
        P = np.array([c.xyz for c in picked])
        picked.append(max(rest, key=lambda c: float(np.min(np.linalg.norm(P - c.xyz, axis=1)))))
    return picked


# --- from a registration ------------------------------------------------------------------------

def sequence_states(rec, cov, ref_ids: set[int], floors: dict[str, float]) -> dict[str, SequenceState]:
    """Per registered sequence of the joint model ``rec`` (pycolmap), its state from the BA
    covariance ``cov`` (pycolmap BACovariance); ``floors``: photo -> systematic centre variance."""
    by_seq: dict[str, list[int]] = {}
    for iid in sorted(rec.reg_image_ids()):
        if iid not in ref_ids:
            by_seq.setdefault(rec.images[iid].name.split("/")[1], []).append(iid)
    out = {}
    for seq, ids in by_seq.items():
        blocks = [[_cross(cov, a, b) for b in ids] for a in ids]
        if any(x is None for row in blocks for x in row):
            continue
        names = [rec.images[i].name for i in ids]
        out[seq] = SequenceState(seq, names, [Pose.from_pycolmap(rec.images[i].cam_from_world()) for i in ids],
                                 [Camera.from_pycolmap(rec.cameras[rec.images[i].camera_id]) for i in ids],
                                 np.block(blocks), np.array([floors.get(n, 0.0) for n in names]))
    return out


def _cross(cov, a: int, b: int) -> np.ndarray | None:
    try:
        c = np.asarray(cov.get_cam_cov_from_world(a) if a == b else cov.get_cam_cross_cov_from_world(a, b))
    except Exception:  # noqa: BLE001 - an image without a covariance block
        return None
    if c.shape != (6, 6) or not np.all(np.isfinite(c)):
        return None
    return _HALF @ c @ _HALF   # Ceres' quaternion tangent is half the rotation vector (gtkit.pose.Pose.from_pycolmap)


_HALF = np.diag([2.0, 2.0, 2.0, 1.0, 1.0, 1.0])


def save_states(path, states: dict[str, SequenceState]) -> None:
    """The sequences' covariances (``sequence_covariance.npz`` beside the registration), so a
    candidate can be scored later without the BA (the benchmark, a later annotation session)."""
    arrays = {}
    for q, s in states.items():
        arrays[f"{q}/names"] = np.array(s.names)
        arrays[f"{q}/cov"] = s.cov
        arrays[f"{q}/floor"] = s.floor
    np.savez_compressed(path, **arrays)


def load_states(path, rec) -> dict[str, SequenceState]:
    """:func:`save_states`' file with the poses and cameras of the joint model ``rec`` it was made with."""
    z = np.load(path)
    out = {}
    for key in z.files:
        if not key.endswith("/names"):
            continue
        q = key[:-len("/names")]
        names = [str(n) for n in z[key]]
        ims = [rec.find_image_with_name(n) for n in names]
        out[q] = SequenceState(q, names, [Pose.from_pycolmap(im.cam_from_world()) for im in ims],
                               [Camera.from_pycolmap(rec.cameras[im.camera_id]) for im in ims],
                               z[f"{q}/cov"], z[f"{q}/floor"])
    return out


def reference_views(ref_rec) -> dict[str, tuple[Pose, Camera]]:
    """Every registered reference photo's (pose, camera) (fixed in the registration)."""
    return {im.name: (Pose.from_pycolmap(im.cam_from_world()), Camera.from_pycolmap(ref_rec.cameras[im.camera_id]))
            for im in ref_rec.images.values() if im.has_pose}


def grid_candidates(state: SequenceState, rec, refs: dict[str, tuple[Pose, Camera]],
                    settings: GuidanceSettings) -> list[Candidate]:
    """One candidate per grid cell of each of the sequence's photos: the block point seen nearest the
    cell's centre, to be clicked there and in the ``reference_views`` reference photos that see it
    from the most similar direction (the reference area)."""
    nx, ny = (int(v) for v in settings.grid)
    out = []
    ref_items = list(refs.items())
    ref_C = np.array([p.center for _, (p, _) in ref_items]).reshape(-1, 3)
    for name, pose, cam in zip(state.names, state.poses, state.cams):
        im = rec.find_image_with_name(name)
        pts = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        if not pts or not ref_items:
            continue
        xy = np.array([p[0] for p in pts])
        X = np.array([p[1] for p in pts])
        for gx in range(nx):
            for gy in range(ny):
                c = np.array([(gx + 0.5) * cam.width / nx, (gy + 0.5) * cam.height / ny])
                inside = ((np.abs(xy[:, 0] - c[0]) <= cam.width / nx / 2) & (np.abs(xy[:, 1] - c[1]) <= cam.height / ny / 2))
                if not inside.any():
                    continue
                i = np.flatnonzero(inside)[np.argmin(np.linalg.norm(xy[inside] - c, axis=1))]
                view = X[i] - pose.center
                seen = []
                for (rn, (rp, rc)), C in zip(ref_items, ref_C):
                    uv, front = rc.project((rp.R @ X[i] + rp.t)[None])
                    if front[0] and rc.in_image(uv[0], margin=0.05 * rc.width):
                        d = X[i] - C
                        seen.append((float(view @ d / np.linalg.norm(view) / np.linalg.norm(d)), rn, uv[0]))
                seen.sort(key=lambda s: -s[0])
                if seen:
                    out.append(Candidate(name, (float(xy[i, 0]), float(xy[i, 1])), X[i],
                                         [(rn, (float(uv[0]), float(uv[1]))) for _, rn, uv in seen[:settings.reference_views]]))
    return out


def sequence_guidance(st: SequenceState, candidates: list[Candidate], refs: dict[str, tuple[Pose, Camera]],
                      settings: GuidanceSettings) -> dict:
    """One registered sequence's record of :func:`guidance`: its sigma now, the ``candidates`` in the
    order to click them (up to the target or ``max_clicks``) with the sigma after each, how many reach
    the target, and whether clicks help at all (``clicks_help``: false where every suggestion together
    would lower the sigma by less than ``min_useful_drop``, the sequence held by its automatic ties)."""
    order = greedy(st, candidates, refs, settings.max_clicks, settings.target_m, settings.click_sigma_px)
    bw = [c.width / settings.grid[0] / 2 for c in st.cams]
    bh = [c.height / settings.grid[1] / 2 for c in st.cams]
    sug = []
    for c, s in order:
        k = st.names.index(c.photo)
        sug.append({"photo": c.photo, "x": c.xy[0], "y": c.xy[1],
                    "box": [max(0.0, c.xy[0] - bw[k]), max(0.0, c.xy[1] - bh[k]),
                            min(float(st.cams[k].width), c.xy[0] + bw[k]), min(float(st.cams[k].height), c.xy[1] + bh[k])],
                    "reference": [{"photo": n, "x": xy[0], "y": xy[1]} for n, xy in c.reference],
                    "ground_xyz": [float(v) for v in c.xyz], "sigma_after_m": s})
    now = st.sigma()
    reach = next((i + 1 for i, (_, s) in enumerate(order) if s <= settings.target_m), None)
    end = sug[-1]["sigma_after_m"] if sug else now
    return {"registered": True, "sigma_m": now, "floor_m": float(np.sqrt(np.mean(st.floor))),
            "target_m": settings.target_m, "at_target": now <= settings.target_m,
            "clicks_to_target": 0 if now <= settings.target_m else reach,
            "sigma_after_suggestions_m": end,
            "clicks_help": bool(now <= settings.target_m or reach is not None
                                or end < (1 - settings.min_useful_drop) * now),
            "suggestions": sug}


def guidance(states: dict[str, SequenceState], rec, refs: dict[str, tuple[Pose, Camera]],
             settings: GuidanceSettings, unregistered: dict[str, list[str]] | None = None) -> dict:
    """The JSON the annotator reads: per sequence its sigma now, the clicks suggested in order (photo,
    pixel, the box to click in, the reference photos and pixels, the sigma expected after each), how
    many reach ``target_m`` (None where the suggestions do not) and the systematic floor clicks cannot
    lower. ``unregistered``: sequence -> its photos, where no covariance exists yet."""
    seqs = {q: sequence_guidance(st, grid_candidates(st, rec, refs, settings), refs, settings)
            for q, st in sorted(states.items())}
    for q, photos in sorted((unregistered or {}).items()):
        if q in seqs or not photos:
            continue
        pick = sorted({photos[0], photos[len(photos) // 2], photos[-1]})
        seqs[q] = {"registered": False, "sigma_m": None, "target_m": settings.target_m, "at_target": False,
                   "clicks_to_target": None, "suggestions": [{"photo": p, "reference": []} for p in pick],
                   "note": "not registered: click 3 or more tie points spread over its photos (first, middle, last)"}
    return {"format": "gtkit-guided-clicks", "version": 1,
            "method": "first-order information gain on the final joint BA's covariance (one pixel a click); "
                      "sigma = RMS over the sequence's photos of sqrt(trace) of the camera-centre covariance",
            "settings": {"target_m": settings.target_m, "max_clicks": settings.max_clicks, "grid": list(settings.grid)},
            "sequences": seqs}


def summary_line(q: str, g: dict) -> str:
    """One line of the GT report for sequence ``q`` of :func:`guidance`'s ``sequences``."""
    if not g.get("registered"):
        return f"{q}: not registered; {g.get('note', '')}"
    if g["at_target"]:
        return f"{q}: sigma {g['sigma_m']:.3f} m, at the {g['target_m']:.2f} m target: no more clicks needed"
    n = g["clicks_to_target"] if g["clicks_to_target"] is not None else len(g["suggestions"])
    if n and not g.get("clicks_help", True):
        floor = f"; systematic floor {g['floor_m']:.3f} m" if g.get("floor_m") else ""
        return (f"{q}: sigma {g['sigma_m']:.3f} m, above the {g['target_m']:.2f} m target, and clicks barely lower it "
                f"({n} suggested: to {g['sigma_after_suggestions_m']:.3f} m{floor}): its automatic tie points hold it "
                "far more than clicks can, so clicking will not bring it to the target")
    photos = list(dict.fromkeys(_stem(s["photo"]) for s in g["suggestions"][:n]))
    where = ", ".join(photos[:6]) + (" ..." if len(photos) > 6 else "")
    if not n:
        return f"{q}: sigma {g['sigma_m']:.3f} m; no click found that lowers it (floor {g['floor_m']:.3f} m)"
    end = (f"expected to bring sigma from {g['sigma_m']:.3f} to {g['suggestions'][n - 1]['sigma_after_m']:.3f} m"
           + ("" if g["clicks_to_target"] is not None else
              f" (the {g['target_m']:.2f} m target is not reached by {n} clicks; systematic floor {g['floor_m']:.3f} m)"))
    return f"{q}: {n} more click{'s' if n != 1 else ''} in photos {where} {end}"


def _stem(name: str) -> str:
    return name.rsplit("/", 1)[-1].rsplit(".", 1)[0]

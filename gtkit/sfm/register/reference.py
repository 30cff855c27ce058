"""The reference block the query sequences are placed in, as the stage uses it: its model, poses and
features (read once, when first needed), and a query photo matched to its 3D points around the poses
the photo's metadata claims (for a photo its sequence's SfM left out, and for a sequence placed
without clicks)."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pycolmap

from ...camera import Camera
from ...errors import GtkitError
from ...photo_positions import PhotoPositions
from ...pose import Pose
from ...project import Project
from ..blocks import QUERIES_STAGE
from ..crossmatch import ReferencePoints, match_photo, match_photo_wide, photo_features
from ..geometry import model_cameras, model_poses
from ..resect import candidate_priors, unregistered_photos
from .bootstrap import Bootstrap, bootstrap_sequence
from .clicked import _place
from .settings import RegisterSettings
from .unguided import keypoint_poses, place_unguided

log = logging.getLogger(__package__)   # the stage's log: gtkit.sfm.register


def _block_georegistered(block_json: Path) -> bool:
    """Whether a query block's SfM was placed in the world by its photos' GPS (its record says so)."""
    if not block_json.is_file():
        return False
    b = json.loads(block_json.read_text())
    return b.get("frame") == "project world frame" and "error" not in (b.get("georegistration") or {})


class ReferenceBlock:
    """The reference model (``ref_dir``) and its feature database (``ref_db``), with the project's
    photos and the stage's settings."""

    def __init__(self, project: Project, ref_dir: Path, ref_db: Path, settings: RegisterSettings):
        self.project, self.P, self.settings = project, project.paths, settings
        self.rec = pycolmap.Reconstruction(ref_dir)
        self.poses, self.cams = model_poses(self.rec), model_cameras(self.rec)
        self.db = ref_db
        self.positions = PhotoPositions(project)
        self._points: ReferencePoints | None = None
        self._left_out_keypoints: dict[str, tuple[dict, str]] = {}   # by sequence: keypoint_poses' answer

    @property
    def cache(self) -> dict:
        """Its poses and cameras, as :func:`gtkit.sfm.register.clicked.register_sequence` takes them."""
        return {"poses": self.poses, "cams": self.cams}

    def points(self) -> ReferencePoints:
        """Its 3D points with their descriptors, read once, when first needed."""
        if self._points is None:
            self._points = ReferencePoints(self.rec, self.db, self.settings.cross.descriptors_per_point)
        return self._points

    @property
    def points_read(self) -> ReferencePoints | None:
        """Its points where already read, else None."""
        return self._points

    def place_clicks(self, obs) -> np.ndarray | None:
        """A tie point's position from its clicks in the reference photos (None where they do not place it)."""
        return _place(obs, self.poses, self.cams, self.rec, self.settings.tie_max_px)[0]

    def gps_centre(self, name: str) -> np.ndarray | None:
        """The photo's position in the project frame (geo.txt first, else EXIF GPS + altitude:
        :mod:`gtkit.photo_positions`), None without one."""
        return self.positions.centre(name)

    def neighbour_priors(self, name: str, k: int = 2) -> list[Pose]:
        """Poses at the photo's GPS position with the attitude of the nearest reference photos (a photo
        held out of the reference flight looks the way its neighbours do), at its GPS height and at
        theirs (consumer altitudes drift)."""
        C = self.gps_centre(name)
        if C is None:
            return []
        refs = sorted(self.poses.values(), key=lambda q: float(np.linalg.norm(q.center[:2] - C[:2])))[:k]
        out = []
        for q in refs:
            out.append(Pose.from_center(q.R, C))
            out.append(Pose.from_center(q.R, np.array([C[0], C[1], q.center[2]])))
        return out

    def solo_block(self, seq: str) -> tuple[pycolmap.Reconstruction | None, str]:
        """A sequence whose SfM made no model: an empty block holding its camera (gtkit.queries'
        resolution: the reference block's calibration of the same camera, else EXIF), to which its
        photos are added one by one as they are resected from automatic matches; or (None, why not)."""
        from ...queries import query_cameras, query_photos

        names = query_photos(self.project, seq)
        if not names:
            return None, f"no query photos in images/queries/{seq}/"
        if not (self.P.stage(QUERIES_STAGE) / seq / "database.db").is_file():
            return None, "no query-block features (run `gtkit sfm DIR --block queries`)"
        try:
            cams = query_cameras(self.project, names)
        except GtkitError as e:
            return None, str(e)
        rec = pycolmap.Reconstruction()
        c = cams[names[0]].camera.to_pycolmap()
        c.camera_id = 1
        rec.add_camera_with_trivial_rig(c)
        return rec, ""

    def left_out_matcher(self, seq: str):
        """``match(name, qrec) -> (Pose | None, n matches, reason)``: a photo of ``seq`` its SfM left out,
        resected from automatic matches to the reference points."""
        return lambda name, qrec: self.match_left_out(seq, name, qrec)

    def match_left_out(self, seq: str, name: str, qrec: pycolmap.Reconstruction):
        """A left-out photo of ``seq`` resected from automatic matches to the reference points."""
        settings, P = self.settings, self.P
        if not settings.cross.enabled or not self.db.is_file():
            return None, 0, "automatic matching is off or the reference database is missing"
        priors = candidate_priors(name, qrec, self.positions.prior_pose)
        # its nearest registered neighbours' poses (in flight order), for a wider search
        order = sorted({im.name for im in qrec.images.values() if im.has_pose} | {name})
        k = order.index(name)
        near = [Pose.from_pycolmap(qrec.find_image_with_name(n).cam_from_world())
                for n in sorted((n for n in order if n != name), key=lambda m: abs(order.index(m) - k))[:2]]
        by_reference = self.neighbour_priors(name)
        priors = priors + by_reference
        feats = photo_features(P.stage(QUERIES_STAGE) / seq / "database.db", name)
        if feats is None:
            return None, 0, "no features in its sequence's database"
        cam = Camera.from_pycolmap(qrec.cameras[sorted(qrec.cameras)[0]])
        if not priors and not near:
            return self._left_out_by_keypoints(seq, name, qrec, cam, "no GPS to guide matching")
        found = [match_photo(p, cam, *feats, self.points(), settings.cross) for p in priors]
        pose, rows, _ = max(found, key=lambda f: len(f[1])) if found else (None, [], [])
        if pose is None and settings.bootstrap.enabled:   # a wider search around its own and its neighbours' poses
            guides = priors[:1] + near + [q for q in by_reference if q is not priors[0]]
            pose, rows = self._match_wider(guides, cam, feats)
        if pose is None:
            return self._left_out_by_keypoints(
                seq, name, qrec, cam, f"fewer than {settings.cross.min_inliers} consistent matches to the reference "
                "points around its metadata pose" + (" or its neighbours' poses" if near else ""))
        return pose, len(rows), ""

    def _left_out_by_keypoints(self, seq: str, name: str, qrec: pycolmap.Reconstruction, cam: Camera, why: str):
        """(pose | None, n reference points it sees, reason) of a left-out photo (its camera ``cam``, the
        sequence's) that ``why`` could not be matched around a pose: registered into the reference block by its keypoints
        (:func:`gtkit.sfm.register.unguided.keypoint_poses`), once for every photo of ``seq`` its SfM left
        out; refused where it lands farther than ``bootstrap.max_offset_m`` from the photo's GPS."""
        settings = self.settings
        if not settings.unguided.enabled:
            return None, 0, why
        if seq not in self._left_out_keypoints:
            sdir = self.P.stage(QUERIES_STAGE) / seq
            posed = {im.name for im in qrec.images.values() if im.has_pose}
            names = sorted(set(unregistered_photos(sdir / "block.json")) - posed) or [name]
            self._left_out_keypoints[seq] = keypoint_poses(self, names, {n: cam for n in names}, sdir / "database.db",
                                                           settings, self.P.stage("register") / "unguided" /
                                                           f"{seq}.left_out")
            log.info("sequence %s: %d of %d photos its SfM left out registered into the reference block by "
                     "keypoint matches with %s", seq, len(self._left_out_keypoints[seq][0]), len(names),
                     self._left_out_keypoints[seq][1])
        found, how = self._left_out_keypoints[seq]
        if name not in found:
            return None, 0, (f"{why}; fewer than {settings.cross.min_inliers} keypoint matches registered it into "
                             f"the reference block ({how})")
        pose, X, _ = found[name]
        far = self._far_from_gps({name: pose.center})
        if far:
            return None, 0, f"{why}; keypoint matches ({how}) {far}"
        return pose, len(X), ""

    def _match_wider(self, guides: list[Pose], cam: Camera, feats):
        """(pose, matched rows) of the best match around ``guides``, wider and wider, at last over the
        whole image: a low photo under consumer GPS and without attitude is hundreds of pixels off, or
        turned, from its guides (Brighton at 35 m with ~10 m GPS: found only with the whole image)."""
        settings = self.settings
        pose, rows = None, []
        r0 = settings.bootstrap.radius_px
        for radius in (r0, 4 * r0, max(cam.width, cam.height)):
            found = [(g, match_photo_wide(g, cam, *feats, self.points(), settings.cross, radius))
                     for g in guides]
            found = [f for g, f in found if f[0] is not None
                     and np.linalg.norm(f[0].center - g.center) <= settings.bootstrap.max_offset_m]
            if found:
                pose, rows, _ = max(found, key=lambda f: len(f[1]))
                break
        return pose, rows

    def place_without_clicks(self, seq: str, qrec: pycolmap.Reconstruction) -> Bootstrap:
        """The sequence placed by its photos' automatic matches (no clicks needed)."""
        settings, P = self.settings, self.P
        if not settings.bootstrap.enabled:
            return Bootstrap(None, "placing sequences by automatic matches is off ([register.bootstrap] enabled)", {})
        if not settings.cross.enabled or not self.db.is_file():
            return Bootstrap(None, "automatic matching is off or the reference database is missing", {})
        sdir = P.stage(QUERIES_STAGE) / seq
        db = sdir / "database.db"
        if not db.is_file():
            return Bootstrap(None, "its sequence's feature database is missing", {})
        georegistered = _block_georegistered(sdir / "block.json")
        cams = model_cameras(qrec)
        names = [im.name for im in qrec.images.values() if im.has_pose]
        if not georegistered and not any(self.positions.prior_pose(n) is not None or self.gps_centre(n) is not None
                                         for n in names):   # nothing to guide a match: every reference photo
            return place_unguided(self, seq, qrec, db, settings)

        def priors(name):
            out = []
            meta = self.positions.prior_pose(name)
            if meta is not None:
                out.append(("metadata", meta))
            if georegistered:
                out.append(("block GPS", Pose.from_pycolmap(qrec.find_image_with_name(name).cam_from_world())))
            return out

        features: dict = {}

        def match(name, prior, wider=True):
            if name not in features:
                features[name] = photo_features(db, name)
            feats = features[name]
            if feats is None:
                return None, np.zeros((0, 3)), np.zeros(0, int)
            ref = self.points()
            radii = (settings.bootstrap.radius_px, 2 * settings.bootstrap.radius_px)
            for radius in radii if wider else radii[:1]:   # then a wider search
                pose, rows, kk = match_photo_wide(prior, cams[name], *feats, ref, settings.cross, radius)
                if pose is not None:
                    break
            return pose, ref.xyz[rows], kk

        out = bootstrap_sequence(qrec, priors, match, settings, self.attitude_search)
        if out.sim is not None or not settings.unguided.enabled:
            return out
        # the poses the metadata gave led nowhere (a block GPS fit turned about its positions' line, an
        # attitude far off): the photos' own keypoints, as for photos without metadata
        alt = place_unguided(self, seq, qrec, db, settings, why="matching around its metadata poses failed")
        far = (self._far_from_gps({im.name: alt.sim * im.projection_center() for im in qrec.images.values()
                                   if im.has_pose}) if alt.sim is not None else None)
        far = f"its photos were {far}" if far else None
        if alt.sim is None or far is not None:
            out.reason += f"; matched without its metadata: {alt.reason or far}"
            return out
        log.info("sequence %s: matching around its metadata poses failed (%s); placed by keypoint matches "
                 "instead", seq, out.reason)
        alt.metadata_failed = out.reason
        return alt

    def _far_from_gps(self, placed: dict[str, np.ndarray]) -> str | None:
        """Why photos placed without their metadata (``placed``: {photo: centre}) contradict their GPS
        positions (the median distance from them over ``bootstrap.max_offset_m``: repeated texture
        matched the wrong place, as on the tiny sample's 8-photo block, 111-134 m off), else None."""
        d = [float(np.linalg.norm(np.asarray(x) - c)) for n, x in placed.items()
             if (c := self.gps_centre(n)) is not None]
        limit = self.settings.bootstrap.max_offset_m
        if d and np.median(d) > limit:
            return (f"placed {np.median(d):.0f} m{' (median)' if len(d) > 1 else ''} from "
                    f"{'their GPS positions' if len(d) > 1 else 'its GPS position'}, more than "
                    f"[register.bootstrap] max_offset_m = {limit:g}: taken for a false match")
        return None

    def attitude_search(self, name: str) -> list[tuple[str, Pose]]:
        """Poses at the photo's GPS position with a grid of attitudes (no gimbal tags), labelled."""
        C = self.gps_centre(name)
        if C is None:
            return []
        b = self.settings.bootstrap
        return [(f"GPS, attitude searched (yaw {yaw:.0f}, pitch {pitch:.0f})", Pose.from_dji(yaw, pitch, 0.0, C))
                for pitch in b.search_pitches_deg for yaw in np.arange(0.0, 360.0, b.search_yaw_step_deg)]

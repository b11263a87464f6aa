"""The 360-degree landmark model: keyframes with poses and features, 3D points, one file.

File format (`.mirage`): a zip archive holding `manifest.json` (format name and version,
camera, detector settings, keyframe names/poses/image sizes, and for every array its
shape, dtype and SHA-256) and one `.npy` per array. Per-keyframe arrays are concatenated
with offsets, so loading is a handful of reads (well under 0.5 s for 36 keyframes).
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from dataclasses import dataclass, field

import cv2
import numpy as np

from . import signals
from .camera import Camera
from .errors import InputError
from .features import DetectorSettings
from .fileio import atomic_path, require_file
from .model_index import DescriptorIndex
from .model_index import point_twins as _twins
from .pose import Pose

FORMAT = "mirage-landmark-model"
FORMAT_VERSION = 1
THUMB_WIDTH = 160
MAX_IMAGE_PX = 2048  # keyframe images stored for patches: longer side at most (halved)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass
class Keyframe:
    """One stored view: pose, all its features, and the link of each feature to a 3D point."""

    name: str
    pose: Pose
    keypoints: np.ndarray  # (N,2) float32, pixels in the distorted image
    descriptors: np.ndarray  # (N,D) of the detector spec's dtype (float32 SIFT, uint8 ORB)
    point_ids: np.ndarray  # (N,) int32 index into LandmarkModel.points, -1 = no 3D point
    thumbnail: np.ndarray  # small grey uint8 image (width THUMB_WIDTH)
    # features of the keyframe's views squashed as from higher up (tilt.py), each linked
    # to one of its points: (keypoints, descriptors, point ids); None: not made
    tilted: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    # the detector's descriptor dtype when `descriptors` was given in the file's form
    # (SIFT's as bytes, memory-mapped): cast on first use, so a load reads none of them
    dtype: object = field(default=None, repr=False, compare=False)
    # the grey image as PNG bytes (uint8), for placing points by their patches
    # (patches.py); `image_scale`: its pixels per keyframe pixel (large images halved)
    image: np.ndarray | None = field(default=None, repr=False, compare=False)
    image_scale: float = 1.0

    def gray_image(self) -> np.ndarray | None:
        """The stored grey image (decoded on each call; None when the model has none). A
        stored image that does not decode (a damaged file) is an InputError."""
        if self.image is None:
            return None
        img = cv2.imdecode(np.asarray(self.image, np.uint8), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(
                f"keyframe {self.name}'s stored image does not decode (the model file is "
                "damaged); rebuild it with 'mirage build-model'"
            )
        return img

    def linked(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keypoints, descriptors, point_ids) of the features that have a 3D point."""
        m = self.point_ids >= 0
        d = self.__dict__["_descriptors"][m]  # the linked rows only, cast
        d = d if self.dtype is None else d.astype(self.dtype, copy=False)
        return self.keypoints[m], d, self.point_ids[m]

    @property
    def n_linked(self) -> int:
        return int(np.count_nonzero(self.point_ids >= 0))

    def compact(self) -> Keyframe:
        """Hold the descriptors (and the squashed views') in their on-disk form, SIFT's as
        bytes (a quarter of the memory: 110 MB less for 144 keyframes), cast back on use."""
        d = self.__dict__["_descriptors"]
        if d.dtype != np.uint8 and _bytes_exactly(d):
            self.dtype = self.dtype or d.dtype
            self.descriptors = d.astype(np.uint8)
        if self.tilted is not None and self.tilted[1].dtype != np.uint8:
            k, t, p = self.tilted
            self.tilted = (k, t.astype(np.uint8) if _bytes_exactly(t) else t, p)
        return self


def _descriptors_get(kf: Keyframe) -> np.ndarray:
    d = kf.__dict__["_descriptors"]
    if kf.dtype is not None and d.dtype != kf.dtype:
        d = kf.__dict__["_descriptors"] = d.astype(kf.dtype)
    return d


def _descriptors_set(kf: Keyframe, value: np.ndarray) -> None:
    kf.__dict__["_descriptors"] = value


Keyframe.descriptors = property(_descriptors_get, _descriptors_set)  # after the dataclass


def encode_image(gray: np.ndarray, max_px: int = MAX_IMAGE_PX) -> tuple[np.ndarray, float]:
    """A keyframe's grey image as lossless PNG bytes, halved (pyrDown: its pixel `x` at
    `x / 2`) until its longer side is at most `max_px`; and that scale."""
    scale = 1.0
    while max(gray.shape[:2]) > max_px:
        gray, scale = cv2.pyrDown(gray), scale / 2
    _, buf = cv2.imencode(".png", gray, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return buf.ravel().astype(np.uint8), scale


def make_thumbnail(gray: np.ndarray, width: int = THUMB_WIDTH) -> np.ndarray:
    h = max(1, round(gray.shape[0] * width / gray.shape[1]))
    return cv2.resize(gray, (width, h), interpolation=cv2.INTER_AREA)


class KeyframeRecognition:
    """Which keyframes see a frame: by its descriptors (global recognition) or by its pose
    (a part of `LandmarkModel`: it reads `keyframes`, `points` and `detector` and keeps the
    indexes in `_index` and `_tilted_index`)."""

    @property
    def has_images(self) -> bool:
        return bool(self.keyframes) and all(kf.image is not None for kf in self.keyframes)

    @property
    def has_tilted(self) -> bool:
        return any(kf.tilted is not None and len(kf.tilted[2]) for kf in self.keyframes)

    def _linked_rows(self, tilted: bool = False):
        """Every keyframe's linked descriptors (`tilted`: and those of its squashed views),
        with the keyframe and the point of each row; filled into one array (the tilted
        rows of 144 keyframes are 53 MB as float)."""
        parts = []
        for kf in self.keyframes:
            m = kf.point_ids >= 0
            part = [(kf.__dict__["_descriptors"], m, kf.point_ids[m])]
            if tilted and kf.tilted is not None and len(kf.tilted[2]):
                part.append((kf.tilted[1], slice(None), kf.tilted[2]))
            parts.append(part)
        dim = self.keyframes[0].__dict__["_descriptors"].shape[1] if self.keyframes else 128
        n = sum(len(p) for part in parts for _, _, p in part)
        D = np.empty((n, dim), self.detector.spec.dtype)
        owner, pids, at = np.empty(n, np.int32), np.empty(n, np.int32), 0
        for i, part in enumerate(parts):
            for d, rows, p in part:
                D[at : at + len(p)] = d[rows]  # cast to the detector's dtype as copied
                owner[at : at + len(p)], pids[at : at + len(p)] = i, p
                at += len(p)
        return D, owner, pids

    def _build_index(self, tilted: bool = False, stored: np.ndarray | None = None):
        """One search over all keyframes' linked descriptors (`tilted`: and those of their
        squashed views), with the owner and point of each row; `stored`: the model file's
        KD-trees of it (`DescriptorIndex`)."""
        alld, owner, pids = self._linked_rows(tilted)
        hamming = self.detector.spec.norm == cv2.NORM_HAMMING
        # the squashed views' trees from a seed of their own: the same trees whether
        # `build-model` stored them or a search builds them (an in-process model, a file
        # made before), so a benchmark measures what the command does; the recognition
        # trees go on from the twins' seed (see DescriptorIndex)
        seed = TILTED_TREE_SEED if tilted else None
        search = DescriptorIndex(alld, hamming, stored, seed=seed) if len(alld) else None
        index = (search, owner, pids)
        if tilted:
            self._tilted_index = index
        else:
            self._index = index
        return index

    def prepare_recognition(self) -> None:
        """Build the recognition index now (FLANN over every linked descriptor: 0.1 s for
        the sample, 0.5-1 s for 144 keyframes; a model file made by this version holds it),
        not in the first frame that needs it."""
        if self._index is None:
            self._build_index(stored=self.tables.get("recognition_index"))

    def twins(self) -> np.ndarray:
        """Per 3D point: has a descriptor twin elsewhere (`point_twins`); the model file's
        table when it holds one (`build-model` makes it), else found now."""
        t = self.tables.get("twins")
        if t is None or len(t) != len(self.points):
            t = self.tables["twins"] = point_twins(self)
        return np.asarray(t, bool)

    def ground(self) -> np.ndarray:
        """Per 3D point: on the ground (`ground_points`); stored or found now."""
        g = self.tables.get("ground")
        if g is None or len(g) != len(self.points):
            g = self.tables["ground"] = ground_points(self.points)
        return np.asarray(g, bool)

    def recognize(
        self, descriptors: np.ndarray, top_k: int = 3, tilted: bool = False
    ) -> list[tuple[int, float]]:
        """Keyframes that most likely see the same side as a frame's descriptors.

        Each query votes for the keyframe of its nearest linked descriptor when it passes
        the ratio test, or when its two nearest neighbours are the same 3D point (seen by
        neighbouring keyframes, which would otherwise fail the ratio test). Votes by chance
        go to each keyframe in proportion to its linked descriptors: the keyframes with more
        votes than that share explains (by two standard deviations) come first, each group
        by votes (a keyframe with many
        points collects many chance votes: on real photographs they outnumbered the true
        keyframe's; counted by votes alone, dtu_scan37's frame 29 was sent to three
        keyframes that see none of its points).
        """
        if len(descriptors) == 0 or not self.keyframes:
            return []
        index = self._tilted_index if tilted else self._index
        if index is None:  # (the tilted views' index: loaded when a relocalisation needs it)
            index = self._build_index(
                tilted, self.tables.get("tilt_recognition_index" if tilted else "recognition_index")
            )
        search, owner, pids = index
        if search is None:
            return []
        q = np.ascontiguousarray(descriptors, dtype=self.detector.spec.dtype)
        i, dist = search.knn(q, 2)
        ok = i[:, 0] >= 0
        i1, i2 = i[:, 0], i[:, 1]
        same = ok & (i2 >= 0) & (pids[np.clip(i2, 0, None)] == pids[np.clip(i1, 0, None)])
        good = ok & ((dist[:, 0] < 0.8 * dist[:, 1]) | same)
        votes = np.bincount(owner[i1[good]], minlength=len(self.keyframes)).astype(float)
        share = np.bincount(owner, minlength=len(self.keyframes)) / max(len(owner), 1)
        chance = votes.sum() * share
        beyond = votes > chance + 2.0 * np.sqrt(chance)  # more votes than chance explains
        order = np.argsort(-votes, kind="stable")
        order = np.concatenate([order[beyond[order]], order[~beyond[order]]])[:top_k]
        return [(int(i), float(votes[i])) for i in order if votes[i] > 0]

    def nearest_keyframes(self, pose: Pose, k: int = 3) -> list[int]:
        """Keyframes whose viewpoint is closest: direction from the landmark to the camera
        centre, plus half the angle between the optical axes (so a camera that turned
        away is not matched to a keyframe that looks the other way)."""
        if not self.keyframes:
            return []
        target, centers, norms, axes = self._views()
        c = pose.center - target
        cos_dir = centers @ c / (norms * np.linalg.norm(c) + 1e-12)
        cos_ax = axes @ pose.R[2]
        d = np.arccos(np.clip(cos_dir, -1, 1)) + 0.5 * np.arccos(np.clip(cos_ax, -1, 1))
        return [int(i) for i in np.argsort(d, kind="stable")[:k]]

    def _views(self):
        """(landmark centre, keyframe centres from it, their lengths, optical axes in W),
        found once: every detection asks for the nearest keyframes."""
        key = (len(self.keyframes), len(self.points))
        if self._view_table is None or self._view_table[0] != key:
            target = self.points.mean(axis=0) if len(self.points) else np.zeros(3)
            centers = np.array([kf.pose.center for kf in self.keyframes]) - target
            axes = np.array([kf.pose.R[2] for kf in self.keyframes])  # optical axis in W
            self._view_table = (key, target, centers, np.linalg.norm(centers, axis=1), axes)
        return self._view_table[1:]

    # --- files --------------------------------------------------------------------------


@dataclass
class LandmarkModel(KeyframeRecognition):
    """Keyframes around the landmark and the 3D points (W frame) their features see.

    `point_observations` is a dict of equal-length int32 arrays `point`, `keyframe`,
    `feature`: point P is seen as feature F of keyframe K.
    """

    camera: Camera
    detector: DetectorSettings
    keyframes: list[Keyframe]
    points: np.ndarray
    point_observations: dict = field(default_factory=dict)
    version: int = FORMAT_VERSION
    meta: dict = field(default_factory=dict)  # build settings: spacing_deg, roi, inputs, ...
    # tables read from the model file or found when first asked: twins, ground (per point)
    # and the recognition index's KD-trees (`_table_arrays`)
    tables: dict = field(default_factory=dict, repr=False, compare=False)
    _index: object = field(default=None, repr=False, compare=False)
    _tilted_index: object = field(default=None, repr=False, compare=False)
    _view_table: object = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        self.points = np.asarray(self.points, float).reshape(-1, 3)
        if not self.point_observations:
            self.point_observations = observations_from_keyframes(self.keyframes)

    # --- geometry summaries -------------------------------------------------------------
    def reprojection_errors(self) -> np.ndarray:
        """Pixel distance between every observation and its point's projection."""
        errs = []
        for kf in self.keyframes:
            kp, _, pid = kf.linked()
            if len(pid):
                uv = self.camera.project(self.points[pid], kf.pose)
                errs.append(np.linalg.norm(uv - kp, axis=1))
        return np.concatenate(errs) if errs else np.zeros(0)

    @property
    def world_from_model(self) -> np.ndarray:
        """3x3 rotation from the model's frame to the user's W (X_w = M X_model). The model
        is kept in a levelled copy of W whose Z is the up axis found at build time
        (`meta['up']`; identity for +Z and for models made before it was recorded)."""
        up = self.meta.get("up") or {}
        return np.array(up.get("world_from_model", np.eye(3)), float).reshape(3, 3)

    def azimuths(self) -> np.ndarray:
        return np.array([kf.pose.azimuth_deg for kf in self.keyframes])

    def summary(self) -> dict:
        """Numbers people check after a build: size, track length, accuracy, coverage."""
        return model_summary(self)

    def save(self, path) -> None:
        """Write the model atomically as one zip file (see the module docstring)."""
        arrays = self._arrays()
        manifest = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "camera": {
                "width": self.camera.width,
                "height": self.camera.height,
                "K": self.camera.K.tolist(),
                "dist": self.camera.dist.tolist(),
                **({"model": self.camera.model} if self.camera.model != "pinhole" else {}),
            },
            "detector": self.detector.to_dict(),
            "keyframes": [
                {
                    "name": kf.name,
                    "R": kf.pose.R.tolist(),  # exact doubles: a round trip changes nothing
                    "t": kf.pose.t.tolist(),
                    "center_m": kf.pose.center.tolist(),  # for people reading the manifest
                    "azimuth_deg": kf.pose.azimuth_deg,
                    "features": len(kf.keypoints),
                    "linked": kf.n_linked,
                    "thumbnail_size": [int(kf.thumbnail.shape[1]), int(kf.thumbnail.shape[0])],
                }
                for kf in self.keyframes
            ],
            "points": len(self.points),
            "meta": self.meta,
            "arrays": {
                k: {"shape": list(a.shape), "dtype": a.dtype.str, "sha256": _sha(a)}
                for k, a in arrays.items()
            },
        }
        with atomic_path(path, suffix=".mirage") as tmp:
            # a signal inside ZipFile() would leave a half-built object whose __del__ prints
            # a traceback on stderr: hold it until the object is whole (then it is raised)
            with signals.deferred():
                zf = zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1)
            # likewise inside writestr: between opening an entry's write handle and its
            # `with`, an interrupt leaves the handle open and close() then raises a
            # ValueError that hides the interrupt; one entry takes milliseconds to write
            with zf as z:
                with signals.deferred():
                    z.writestr("manifest.json", json.dumps(manifest, indent=1).encode())
                for k in list(arrays):  # one array's bytes at a time (memory)
                    buf = io.BytesIO()
                    np.save(buf, arrays.pop(k), allow_pickle=False)
                    kind = zipfile.ZIP_STORED if f"{k}.npy" in _MAPPED else zipfile.ZIP_DEFLATED
                    with signals.deferred():
                        z.writestr(f"{k}.npy", buf.getbuffer(), compress_type=kind)
                    del buf

    def _arrays(self) -> dict[str, np.ndarray]:
        kfs = self.keyframes
        counts = np.array([len(kf.keypoints) for kf in kfs], np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        desc = [kf.__dict__["_descriptors"] for kf in kfs]  # as held: a loaded one's bytes
        dim = desc[0].shape[1] if desc else 128
        all_desc = _stored_descriptors(desc, dim)
        thumbs = [kf.thumbnail for kf in kfs]
        th_shapes = np.array([t.shape[:2] for t in thumbs], np.int64).reshape(-1, 2)
        obs = self.point_observations
        return {
            "offsets": offsets,
            "keypoints": np.concatenate([kf.keypoints for kf in kfs]).astype(np.float32)
            if kfs
            else np.zeros((0, 2), np.float32),
            "descriptors": np.ascontiguousarray(all_desc),
            "point_ids": np.concatenate([kf.point_ids for kf in kfs]).astype(np.int32)
            if kfs
            else np.zeros(0, np.int32),
            "thumb_shapes": th_shapes,
            "thumbnails": np.concatenate([t.ravel() for t in thumbs]).astype(np.uint8)
            if thumbs
            else np.zeros(0, np.uint8),
            "points": self.points.astype(np.float64),
            "obs_point": np.asarray(obs.get("point", []), np.int32),
            "obs_keyframe": np.asarray(obs.get("keyframe", []), np.int32),
            "obs_feature": np.asarray(obs.get("feature", []), np.int32),
            **self._tilted_arrays(dim),
            **_image_arrays(self.keyframes),
            **self._table_arrays(),
        }

    def _table_arrays(self) -> dict[str, np.ndarray]:
        """What tracking needs before its first frame, found once here rather than at every
        `mirage track` start: the twins and ground tables and the recognition KD-trees."""
        tables = {"twins": self.twins().astype(np.uint8), "ground": self.ground().astype(np.uint8)}
        if INHERITED_TABLE in self.tables:  # (an extended model's: not found again)
            tables[INHERITED_TABLE] = np.asarray(self.tables[INHERITED_TABLE], np.float64)
        self.prepare_recognition()  # after the twins: the trees `track` built from them
        tables["recognition_index"] = _index_bytes(self._index[0])
        if self.has_tilted:  # the squashed views' trees: `track` built them at its first
            # relocalisation, inside the tracking (0.9 s for 144 keyframes); now here, once.
            # Each index holds its rows as float twice (FLANN keeps a copy) and its trees:
            # 67 and 165 MB for 144 keyframes, so the first is let go before the second is
            # built (the build's peak 762 -> ~700 MB); a later search loads their bytes
            self._index = None
            self.tables["recognition_index"] = tables["recognition_index"]
            had = self._tilted_index
            tables["tilt_recognition_index"] = _index_bytes((had or self._build_index(True))[0])
            self._tilted_index = None
            self.tables["tilt_recognition_index"] = tables["tilt_recognition_index"]
        return tables

    def _tilted_arrays(self, dim: int) -> dict[str, np.ndarray]:
        """The squashed views' features (tilt.py), concatenated like the keyframes'."""
        if not self.has_tilted:
            return {}
        parts = [
            kf.tilted if kf.tilted is not None else (np.zeros((0, 2)), np.zeros((0, dim)), [])
            for kf in self.keyframes
        ]
        counts = [len(p[2]) for p in parts]
        desc = _stored_descriptors([np.asarray(p[1]) for p in parts], dim)
        return {
            "tilt_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            "tilt_keypoints": np.concatenate([p[0] for p in parts]).astype(np.float32),
            "tilt_descriptors": np.ascontiguousarray(desc),
            "tilt_point_ids": np.concatenate([np.asarray(p[2]) for p in parts]).astype(np.int32),
        }

    @classmethod
    def load(cls, path) -> LandmarkModel:
        """Read a model; a corrupt, truncated or incompatible file is an InputError."""
        p = require_file(path, "model file")
        hint = "rebuild it with 'mirage build-model'"
        try:
            with zipfile.ZipFile(p) as z:
                try:
                    manifest = json.loads(z.read("manifest.json"))
                except KeyError:
                    raise InputError(f"{p} is not a mirage model (no manifest)") from None
                if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
                    raise InputError(f"{p} is not a mirage landmark model")
                version = manifest.get("version")
                if version != FORMAT_VERSION:
                    raise InputError(
                        f"model {p} has format version {version}, this mirage reads version "
                        f"{FORMAT_VERSION}; {hint}"
                    )
                arrays = {
                    name: _read_array(z, p, name, info, hint)
                    for name, info in manifest["arrays"].items()
                }
        except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError) as e:
            raise InputError(f"model {p} is corrupt or truncated ({e}); {hint}") from None
        except (KeyError, TypeError) as e:
            raise InputError(f"model {p} has an invalid manifest ({e}); {hint}") from None
        try:
            return cls._from_parts(manifest, arrays)
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise InputError(
                f"model {p} is incompatible ({type(e).__name__}: {e}); {hint}"
            ) from None

    @classmethod
    def _from_parts(cls, manifest: dict, a: dict) -> LandmarkModel:
        c = manifest["camera"]
        camera = Camera(
            np.array(c["K"]),
            np.array(c["dist"]),
            c["width"],
            c["height"],
            model=c.get("model", "pinhole"),
        )
        detector = DetectorSettings.from_dict(manifest["detector"])
        dtype = np.dtype(detector.spec.dtype)  # descriptors stay in the file until used
        desc, cast = a["descriptors"], dtype if a["descriptors"].dtype != dtype else None
        off, th_off = a["offsets"], np.concatenate([[0], np.cumsum(np.prod(a["thumb_shapes"], 1))])
        kfs = []
        for i, info in enumerate(manifest["keyframes"]):
            s, e = int(off[i]), int(off[i + 1])
            h, w = (int(v) for v in a["thumb_shapes"][i])
            kfs.append(
                Keyframe(
                    info["name"],
                    Pose(np.array(info["R"], float), np.array(info["t"], float)),
                    a["keypoints"][s:e],
                    desc[s:e],
                    a["point_ids"][s:e],
                    a["thumbnails"][th_off[i] : th_off[i + 1]].reshape(h, w),
                    dtype=cast,
                )
            )
        if "tilt_offsets" in a:  # models made with squashed views (tilt.py)
            to = a["tilt_offsets"]
            td = a["tilt_descriptors"]  # as stored: cast where matched
            for i, kf in enumerate(kfs):
                s, e = int(to[i]), int(to[i + 1])
                kf.tilted = (a["tilt_keypoints"][s:e], td[s:e], a["tilt_point_ids"][s:e])
        _attach_images(kfs, a)
        obs = {"point": a["obs_point"], "keyframe": a["obs_keyframe"], "feature": a["obs_feature"]}
        tables = {k: a[k] for k in _TABLES if k in a}
        version, meta = int(manifest["version"]), manifest["meta"]
        return cls(camera, detector, kfs, a["points"], obs, version, meta, tables)


def _image_arrays(keyframes: list[Keyframe]) -> dict[str, np.ndarray]:
    """The keyframes' PNG images, concatenated like their features (none unless all have
    one)."""
    if not keyframes or any(kf.image is None for kf in keyframes):
        return {}
    imgs = [np.asarray(kf.image, np.uint8) for kf in keyframes]
    offsets = np.concatenate([[0], np.cumsum([len(b) for b in imgs])]).astype(np.int64)
    return {
        "image_offsets": offsets,
        "image_scales": np.array([kf.image_scale for kf in keyframes], np.float64),
        "images": np.concatenate(imgs),
    }


def _attach_images(kfs: list[Keyframe], a: dict) -> None:
    """Each keyframe's stored image (a slice of the memory-mapped array), when the model
    was made with them."""
    if "image_offsets" in a:
        off, scales, images = a["image_offsets"], a["image_scales"], a["images"]
        if len(off) != len(kfs) + 1 or len(scales) != len(kfs) or np.any(np.diff(off) < 0):
            raise ValueError("the keyframe images' table does not match the keyframes")
        if off[0] != 0 or off[-1] != len(images):
            raise ValueError("the keyframe images' table does not match the images")
        for i, kf in enumerate(kfs):
            kf.image = images[int(off[i]) : int(off[i + 1])]
            kf.image_scale = float(scales[i])
            # a PNG's signature: checked here, a damaged image is an error before tracking
            # (not inside it); decoding every image would cost 3 ms a keyframe at load
            if bytes(kf.image[:8]) != PNG_SIGNATURE:
                raise ValueError(f"keyframe {kf.name}'s stored image is not a PNG image")
            if bytes(kf.image[-8:-4]) != b"IEND":  # the last chunk: a PNG cut short
                raise ValueError(f"keyframe {kf.name}'s stored image is cut short")
            if not (np.isfinite(kf.image_scale) and 0 < kf.image_scale <= 1):
                raise ValueError(f"keyframe {kf.name}'s image scale {kf.image_scale} is invalid")


def model_summary(model: LandmarkModel) -> dict:
    """Numbers people check after a build: size, track length, accuracy, coverage."""
    err = model.reprojection_errors()
    linked = np.array([kf.n_linked for kf in model.keyframes]) if model.keyframes else [0]
    obs = model.point_observations.get("point", np.zeros(0))
    gap, coverage, spacing = azimuth_gaps(model.azimuths())
    return {
        "keyframes": len(model.keyframes),
        "points": len(model.points),
        "observations": int(len(obs)),
        "mean_track_length": float(len(obs) / max(1, len(model.points))),
        "linked_per_keyframe_min": int(np.min(linked)),
        "linked_per_keyframe_median": float(np.median(linked)),
        "mean_reprojection_px": float(err.mean()) if err.size else float("nan"),
        "rms_reprojection_px": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
        "azimuth_coverage_deg": coverage,
        "largest_gap_deg": gap,
        "spacing_deg": spacing,
        "detector": model.detector.name,
    }


def point_twins(model: LandmarkModel, separation_m: float = 0.05, k: int = 4) -> np.ndarray:
    """Per 3D point: True when one of its descriptors has a near twin at another 3D place
    (`model_index.point_twins`: repeated texture, which must not decide a pose alone)."""
    D, _, P = model._linked_rows()
    hamming = model.detector.spec.norm == cv2.NORM_HAMMING
    return _twins(D, P, model.points, hamming, separation_m, k)


def ground_points(
    points: np.ndarray,
    tol_m: float = 0.03,
    min_share: float = 0.03,
    max_below: float = 0.05,
    max_share: float = 0.9,
    min_off: int = 100,
) -> np.ndarray:
    """Per 3D point: True when it lies on the ground the landmark stands on.

    The ground is seen around the landmark from every side, so its texture (tiles, grass,
    asphalt) can give a pose without the landmark in view, often a wrong one a period
    away: a pose must rest on the landmark's own points. W is Z up (brief, section 3), so
    the ground is the lowest horizontal layer (+-`tol_m`, which absorbs the depth error
    of far floor points) holding at least `min_share` of the points, with almost nothing
    (`max_below`) under it, that reaches out well beyond the rest of the points (1.5x
    their horizontal radius). A model that is nearly all one layer (more than `max_share`)
    with fewer than `min_off` points above it is a flat landmark: nothing is flagged. With
    as many above it, the layer is a floor around a small landmark however many points it
    holds: grass a few metres across gave far tuning seeds 73 and 80 (a 0.3-0.45 m
    landmark, 91-93% of the points on the floor, a third of them with descriptor twins)
    64 and 150 poses relocalised on the floor's next copy, 2-3 m off, that the model's
    own patch of grass could not tell from itself.
    """
    P = np.asarray(points, float).reshape(-1, 3)
    ground = np.zeros(len(P), bool)
    if len(P) < 20:
        return ground
    z = np.sort(P[:, 2])
    # points within +-tol of each candidate height, by two binary searches (no loop)
    n_in = np.searchsorted(z, z + tol_m, "right") - np.searchsorted(z, z - tol_m, "left")
    dense = np.flatnonzero(n_in >= min_share * len(z))
    if not len(dense):
        return ground
    lowest = dense[0]  # the lowest dense layer; then its densest height within tol
    near = np.flatnonzero(np.abs(z - z[lowest]) <= tol_m)
    best = near[np.argmax(n_in[near])]
    h = float(np.median(z[np.abs(z - z[best]) <= tol_m]))
    on = np.abs(P[:, 2] - h) <= tol_m
    share, below = on.mean(), np.mean(P[:, 2] < h - tol_m)
    flat = share > max_share and (~on).sum() < min_off
    if share < min_share or flat or below > max_below or on.all():
        return ground
    # ground reaches out around the landmark; the landmark's own lowest band does not
    c = np.median(P[~on, :2], axis=0)
    r_on = np.percentile(np.hypot(*(P[on, :2] - c).T), 90)
    r_off = np.percentile(np.hypot(*(P[~on, :2] - c).T), 90)
    return on if r_on > 1.5 * r_off else ground


def periodic_floor(points: np.ndarray, twins: np.ndarray, min_off: int = 100) -> np.ndarray:
    """Per 3D point: on a floor whose texture repeats, even one that holds more than 90% of the
    model's points (`ground_points` left those alone before stop 54, and a model's stored
    ground table may still come from then; a fresh table already holds every point this
    flags). When most of the lowest layer's points have descriptor twins, every point of it
    has a copy one period away, found or not (a copy seen from another distance describes
    differently), so none may decide a relocalisation: tuning seed above 7, a small landmark
    on grass repeating every 0.85 m (11 308 of 11 743 points on the floor, 70% twins), was
    relocalised a period away with 51 floor inliers, 12 frames 85 cm off. The landmark needs
    `min_off` points of its own above the layer."""
    layer = ground_points(points, max_share=1.0)
    if (~layer).sum() < min_off or not layer.any() or twins[layer].mean() < 0.5:
        return np.zeros(len(layer), bool)
    return layer


def _stored_descriptors(parts: list[np.ndarray], dim: int) -> np.ndarray:
    """The parts' descriptors, concatenated in their on-disk form: SIFT's are integers
    0..255 held as float, bytes on disk, lossless (`load` casts back to the detector's
    dtype); RootSIFT's are not integers and stay float. Part by part: no float copy of all
    (147 MB for 144 keyframes)."""
    if not parts:
        return np.zeros((0, dim), np.float32)
    if all(_bytes_exactly(p) for p in parts):
        return np.concatenate([p.astype(np.uint8, copy=False) for p in parts])
    return np.concatenate(parts)


def _bytes_exactly(d: np.ndarray) -> bool:
    if d.dtype == np.uint8 or d.size == 0:
        return True
    return bool(np.array_equal(d, np.round(d)) and d.min() >= 0 and d.max() <= 255)


def observations_from_keyframes(keyframes: list[Keyframe]) -> dict[str, np.ndarray]:
    pts, kfi, feat = [], [], []
    for i, kf in enumerate(keyframes):
        f = np.flatnonzero(kf.point_ids >= 0)
        pts.append(kf.point_ids[f])
        kfi.append(np.full(len(f), i))
        feat.append(f)
    cat = (lambda xs: np.concatenate(xs).astype(np.int32)) if keyframes else None
    if cat is None:
        return {k: np.zeros(0, np.int32) for k in ("point", "keyframe", "feature")}
    return {"point": cat(pts), "keyframe": cat(kfi), "feature": cat(feat)}


# How far in azimuth from its nearest keyframe a frame is surely tracked, measured on the
# sample orbit with the keyframes of one side left out: an 80 deg gap, every frame ok (up
# to 40 deg from a keyframe, entering it from a tracked side); 100 deg, 98% at 20-30 deg
# and 57-82% at 30-50; 120 deg, 69% at 20-30 and none beyond; never a wrong pose. Every
# frame within 20 deg of a keyframe was ok in all three, and keyframes every 40 deg track
# the whole orbit.
REACH_DEG = 20.0


def azimuth_gaps(azimuths_deg, reach_deg: float = REACH_DEG) -> tuple[float, float, float]:
    """(largest gap between neighbouring keyframe azimuths, coverage, median spacing) in
    degrees. Coverage: the azimuths within `reach_deg` of a keyframe, where a frame is
    tracked whatever the keyframes' nominal spacing (36 views every 10 deg, 18 every 20 and
    9 every 40 all cover 360 deg; a missing side shows as its hole beyond the reach)."""
    a, gaps = _azimuth_steps(azimuths_deg)
    if a.size == 0:
        return 360.0, 0.0, 0.0
    excess = np.clip(gaps - 2 * reach_deg, 0, None).sum()
    return float(gaps.max()), float(np.clip(360.0 - excess, 0.0, 360.0)), float(np.median(gaps))


def largest_azimuth_gap(azimuths_deg) -> tuple[float, float, float]:
    """(size, from, to) of the largest gap between neighbouring keyframe azimuths, deg."""
    a, gaps = _azimuth_steps(azimuths_deg)
    if a.size == 0:
        return 360.0, 0.0, 360.0
    k = int(np.argmax(gaps))
    return float(gaps[k]), float(a[k]), float(np.mod(a[k] + gaps[k], 360.0))


def _azimuth_steps(azimuths_deg) -> tuple[np.ndarray, np.ndarray]:
    """Distinct azimuths in [0, 360) (to 0.1 deg: elevation bands share them) and the gap
    from each to the next, around the circle."""
    a = np.unique(np.round(np.mod(np.asarray(azimuths_deg, float), 360.0), 1))
    return a, np.diff(np.concatenate([a, a[:1] + 360.0]))


TILTED_TREE_SEED = 0  # a fixed seed (as the twins'): the trees depend on the model alone

# what a model file may hold besides its keyframes and points (`_table_arrays`); a file
# without them (made before) gets them built when first needed
# per point, the sigma (m, rad) it carries from the tracked frames that triangulated it, in
# a model extended by a video (extend.py); absent: every point is the keyframes' own
INHERITED_TABLE = "inherited"
_TABLES = ("twins", "ground", "recognition_index", "tilt_recognition_index", INHERITED_TABLE)

# arrays stored uncompressed and memory-mapped at load: a keyframe's descriptors are read
# when it is first matched (SIFT's bytes compress to 80%: not worth inflating at every load);
# the KD-trees (13 MB deflated to 4 for 144 keyframes: 70 ms of every start to inflate)
# and the thumbnails (the viewer's only) likewise
_MAPPED = {
    "descriptors.npy",
    "tilt_descriptors.npy",
    "recognition_index.npy",
    "tilt_recognition_index.npy",
    "thumbnails.npy",
    "images.npy",
}


def _read_array(z: zipfile.ZipFile, path, name: str, info: dict, hint: str) -> np.ndarray:
    """One array of a model file, checked against its manifest entry: memory-mapped when
    stored uncompressed, else inflated."""
    try:
        zi = z.getinfo(f"{name}.npy")
    except KeyError:
        raise InputError(f"model {path} is incomplete (no {name}); {hint}") from None
    a = _mapped(z, zi, path) if zi.compress_type == zipfile.ZIP_STORED else None
    if a is None:
        a = np.load(io.BytesIO(z.read(zi)), allow_pickle=False)
    if list(a.shape) != info["shape"] or _sha(a) != info["sha256"]:
        raise InputError(f"model {path} is corrupt ({name} checksum); {hint}")
    return a


def _mapped(z: zipfile.ZipFile, zi: zipfile.ZipInfo, path) -> np.ndarray | None:
    """The .npy member `zi` (stored, not compressed) as a read-only memory map of the file;
    None when it cannot be (then it is read)."""
    with z.open(zi) as f:
        version = np.lib.format.read_magic(f)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else None
        if read is None and version == (2, 0):
            read = np.lib.format.read_array_header_2_0
        if read is None:
            return None
        shape, fortran, dtype = read(f)
        header = f.tell()
    if fortran or dtype.hasobject or not shape or 0 in shape:
        return None
    z.fp.seek(zi.header_offset)
    local = z.fp.read(30)  # the local file header: its name and extra field lengths
    if local[:4] != b"PK\x03\x04":
        return None
    start = zi.header_offset + 30 + int.from_bytes(local[26:28], "little")
    start += int.from_bytes(local[28:30], "little") + header
    return np.memmap(path, dtype, "r", start, shape)


def _index_bytes(search) -> np.ndarray:
    """A DescriptorIndex's KD-trees as stored (empty: no index)."""
    return search.to_bytes() if search is not None else np.zeros(0, np.uint8)


def _sha(a: np.ndarray) -> str:
    a = np.ascontiguousarray(a)
    return hashlib.sha256(a.data if a.size else b"").hexdigest()

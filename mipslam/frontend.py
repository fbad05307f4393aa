"""Wide-basin tracking front-end: ORB features with depth, matched to a reference frame, pose by PnP RANSAC.

Render-based tracking (:mod:`mipslam.tracking`) refines a pose by gradient steps on a photometric and
depth loss; its basin is a few pixels of image motion. Under fast hand-held motion (TUM fr1_rpy turns
the camera by up to 5 degrees between frames, 20-30 px at 320x240) the constant-velocity guess falls
outside that basin. This module gives tracking a start that holds for any motion the features survive,
as feature front-ends do in RGB-D SLAM (ORB-SLAM's RGB-D tracking; Photo-SLAM puts ORB-SLAM3 in front of
a Gaussian map):

1. :func:`extract_features`: ORB keypoints and descriptors (Rublee et al., 2011) on the grey image, and
   each keypoint's 3D point in its camera frame from the depth image (NaN where depth is missing);
2. :func:`estimate_relative_pose`: brute-force Hamming matching from the current frame's keypoints to the
   reference's (mutual nearest neighbours that pass Lowe's ratio test), then the perspective-n-point
   problem of the reference's 3D points against the current frame's 2D keypoints in RANSAC (OpenCV's
   ``solvePnPRansac``, SQPnP minimal solver, Terzakis & Lourakis 2020), refined by Levenberg-Marquardt on
   the inliers. The result is ``T_rc`` (current camera -> reference camera) with its inlier count;
3. the result is trusted (``ok``) when at least ``min_inliers`` matches agree and they are at least
   ``min_inlier_ratio`` of the matches: fewer means the frames do not share enough structure (blur,
   a blank wall, a different place), and the caller falls back to its motion model and flags the frame.

The functions are pure (numpy / torch in, value objects out). :class:`Frontend` is the tracking stage's
use of them: it caches each frame's features (recomputed on a miss, so a resumed run sees the same
values), starts a frame from the previous tracked frame, and relocalises a lost frame against keyframes.
Conventions (docs/design.md): OpenCV camera, ``T_ab`` maps frame-b points into frame a, metres, pixels with
integer centres.
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Sequence

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree

from mipslam.config import FrontendConfig
from mipslam.render import compiled_library
from mipslam.types import Frame, Intrinsics

_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)
ORB_SCALE_FACTOR = 1.2  # between ORB's pyramid levels: a keypoint of level l is found at 1.2^l px precision


@dataclass(frozen=True)
class FeatureOptions:
    """The front-end's constants: feature extraction, matching, pose estimation, relocalisation (the
    ``frontend`` config section only chooses the method)."""

    num_features: int = 1000  # ORB keypoints per frame
    pyramid_levels: int = 4  # ORB scale pyramid levels (factor 1.2 each)
    fast_threshold: int = 12  # FAST corner threshold (grey levels of 255)
    ratio_test: float = 0.85  # Lowe's ratio: best match distance < ratio * second best
    guided_radius: float = 0.1  # guided search radius around the prior's projection, fraction of the image size
    max_hamming: int = 64  # matches with a larger descriptor distance are dropped (of 256 bits)
    ransac_reprojection_px: float = 3.0  # RANSAC inlier threshold in pixels at the image's resolution
    ransac_iterations: int = 200
    ransac_confidence: float = 0.999
    min_inliers: int = 25  # fewer agreeing matches: the pose is not trusted
    min_inlier_ratio: float = 0.25  # inliers / matches below this: not trusted
    max_prior_jump_m: float = 0.3  # with a prior: a PnP pose further than this from it is not trusted
    max_prior_jump_deg: float = 30.0
    min_depth_m: float = 0.1  # depth outside [min, max] does not give a 3D point
    max_depth_m: float = 8.0
    relocalise_keyframes: int = 8  # a frame whose tracking failed is matched to this many newest keyframes


@dataclass(frozen=True)
class FrameFeatures:
    """ORB features of one frame.

    keypoints: [M, 2] float32 pixel coordinates (u, v)
    descriptors: [M, 32] uint8 ORB descriptors (empty [0, 32] when none)
    points_c: [M, 3] float64 3D points in the frame's camera (metres), NaN rows without depth
    octaves: [M] int64 scale-pyramid level each keypoint was found at (0 = full resolution); None: not known
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    points_c: np.ndarray
    octaves: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


@dataclass(frozen=True)
class RelativePose:
    """Outcome of :func:`estimate_relative_pose`.

    T_rc: [4, 4] float64 current camera -> reference camera (the identity when nothing was found)
    matches: descriptor matches with a 3D point in the reference
    inliers: matches that agree with T_rc within the RANSAC threshold
    reprojection_px: RMS reprojection error of the inliers (pixels; NaN when none)
    ok: inliers >= min_inliers and inliers / matches >= min_inlier_ratio
    reason: "" when ok, else why not ("too_few_matches", "pnp_failed", "too_few_inliers", "low_inlier_ratio",
        "far_from_prior")
    """

    T_rc: torch.Tensor
    matches: int
    inliers: int
    reprojection_px: float
    ok: bool
    reason: str


def _grey_u8(color: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> [H, W] uint8 luma (BT.601)."""
    rgb = color.detach().to("cpu", torch.float32).numpy()
    grey = rgb @ _LUMA if rgb.ndim == 3 else rgb
    return np.clip(grey * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _detector(options: FeatureOptions, image_size: tuple[int, int]):
    edge = max(8, min(31, min(image_size) // 16))  # keep features near the border of small images
    return cv2.ORB_create(nfeatures=options.num_features, scaleFactor=ORB_SCALE_FACTOR,
                          nlevels=options.pyramid_levels,
                          edgeThreshold=edge, patchSize=edge, fastThreshold=options.fast_threshold)


@dataclass(frozen=True)
class Keypoints:
    """ORB keypoints of one image, before depth gives them 3D points (:func:`detect_keypoints`).

    uv: [M, 2] float32 pixel coordinates; descriptors: [M, 32] uint8; octaves: [M] int64 pyramid levels
    """

    uv: np.ndarray
    descriptors: np.ndarray
    octaves: np.ndarray


def detect_keypoints(
    color: torch.Tensor,  # [H, W, 3] float in [0, 1]
    options: FeatureOptions,
) -> Keypoints:
    """ORB keypoints and descriptors of the grey image (module docstring, step 1); the colour alone decides them."""
    grey = _grey_u8(color)
    keypoints, descriptors = _detector(options, grey.shape).detectAndCompute(grey, None)
    if descriptors is None or not keypoints:
        return Keypoints(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros(0, np.int64))
    return Keypoints(np.array([k.pt for k in keypoints], dtype=np.float32), descriptors,
                     np.array([k.octave for k in keypoints], dtype=np.int64))


def lift_keypoints(
    keypoints: Keypoints,
    depth: torch.Tensor,  # [H, W] metres, 0 = no measurement
    intrinsics: Intrinsics,
    options: FeatureOptions,
) -> FrameFeatures:
    """Each keypoint's 3D point in its camera frame from the depth at its nearest pixel (NaN rows without a depth
    in ``[min_depth_m, max_depth_m]``)."""
    uv = keypoints.uv
    if len(uv) == 0:
        return FrameFeatures(uv, keypoints.descriptors, np.zeros((0, 3)), keypoints.octaves)
    depth_np = depth.detach().to("cpu", torch.float32).numpy()
    col = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, depth_np.shape[1] - 1)
    row = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, depth_np.shape[0] - 1)
    z = depth_np[row, col].astype(np.float64)  # [M]
    valid = np.isfinite(z) & (z >= options.min_depth_m) & (z <= options.max_depth_m)
    points = np.full((len(uv), 3), np.nan)
    points[valid, 0] = (uv[valid, 0] - intrinsics.cx) / intrinsics.fx * z[valid]
    points[valid, 1] = (uv[valid, 1] - intrinsics.cy) / intrinsics.fy * z[valid]
    points[valid, 2] = z[valid]
    return FrameFeatures(uv, keypoints.descriptors, points, keypoints.octaves)


def extract_features(
    color: torch.Tensor,  # [H, W, 3] float in [0, 1]
    depth: torch.Tensor,  # [H, W] metres, 0 = no measurement
    intrinsics: Intrinsics,
    options: FeatureOptions,
) -> FrameFeatures:
    """ORB keypoints, descriptors and back-projected 3D points of one frame (module docstring, step 1)."""
    return lift_keypoints(detect_keypoints(color, options), depth, intrinsics, options)


def match_features(query: np.ndarray, train: np.ndarray, ratio: float, max_hamming: int,
                   candidates: np.ndarray | None = None) -> np.ndarray:
    """Mutual nearest neighbours by Hamming distance that pass the ratio test.

    query [M, 32], train [N, 32] uint8 -> [K, 2] int64 pairs (query row, train row), by query row.
    candidates: [P, 2] int64 (query row, train row), the pairs that may match (guided search); None allows all.
    """
    if len(query) < 2 or len(train) < 2:
        return np.zeros((0, 2), np.int64)
    if candidates is not None:
        return _match_candidates(query, train, candidates, ratio, max_hamming)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    return mutual_ratio_pairs(matcher.knnMatch(query, train, k=2), matcher.match(train, query), ratio, max_hamming)


def mutual_ratio_pairs(forward, backward, ratio: float, max_hamming: int) -> np.ndarray:
    """The pairs of OpenCV brute-force matches that pass the ratio test and are mutual.

    forward: ``knnMatch(query, train, k=2)``'s lists; backward: ``match(train, query)``'s matches.
    -> [K, 2] int64 pairs (query row, train row), by query row.
    """
    nearest_query = {m.queryIdx: m.trainIdx for m in backward}
    pairs = []
    for nearest in forward:
        if not nearest:
            continue
        best = nearest[0]
        if best.distance > max_hamming or (len(nearest) > 1 and best.distance >= ratio * nearest[1].distance):
            continue
        if nearest_query.get(best.trainIdx) == best.queryIdx:
            pairs.append((best.queryIdx, best.trainIdx))
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def hamming_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distance of each row pair.  a, b [P, 32] uint8 (or their [P, 4] uint64 views) -> [P] int64"""
    xor = np.bitwise_xor(_as_words(a), _as_words(b))  # [P, 4] uint64
    if not hasattr(np, "bitwise_count"):  # numpy < 2.0
        return np.unpackbits(xor.view(np.uint8), axis=1).sum(axis=1, dtype=np.int64)
    counts = np.bitwise_count(xor).view(np.uint32).ravel()  # [P]: four bytes, each word's count (<= 64)
    pairs = (counts & 0x00FF00FF) + ((counts >> 8) & 0x00FF00FF)  # two 16-bit sums of two bytes each
    return ((pairs & 0xFFFF) + (pairs >> 16)).astype(np.int64)


def _as_words(descriptors: np.ndarray) -> np.ndarray:
    """[P, 32] uint8 ORB descriptors as [P, 4] uint64 (a view where they are contiguous)."""
    if descriptors.dtype == np.uint64:
        return descriptors
    return np.ascontiguousarray(descriptors).view(np.uint64)


def _nearest_per_row(rows: np.ndarray, columns: np.ndarray, distances: np.ndarray, n_rows: int, n_columns: int,
                     with_second: bool = True):
    """For each row: its nearest column (-1 where it has no candidate) and distance, and the second-nearest
    distance (inf where it has fewer than two candidates; None unless ``with_second``). Ties go to the lower
    column, as OpenCV's brute-force matcher breaks them. rows, columns, distances [P] (each (row, column) at most
    once) -> 3 x [n_rows]"""
    none = np.iinfo(np.int64).max
    key = distances * n_columns + columns  # orders by distance, then column
    best = np.full(n_rows, none, dtype=np.int64)
    np.minimum.at(best, rows, key)
    found = best != none
    nearest = np.where(found, best % n_columns, -1)
    nearest_distance = np.where(found, best // n_columns, np.inf).astype(np.float64)
    if not with_second:
        return nearest, nearest_distance, None
    second = np.full(n_rows, none, dtype=np.int64)
    np.minimum.at(second, rows, np.where(key != best[rows], distances, none))
    return nearest, nearest_distance, np.where(second != none, second, np.inf).astype(np.float64)


def _match_candidates(query: np.ndarray, train: np.ndarray, candidates: np.ndarray, ratio: float,
                      max_hamming: int) -> np.ndarray:
    """:func:`match_features` among candidate pairs: what the brute-force matcher with the pairs as its mask
    finds, from the candidates' distances alone (a guided search has tens of candidates per keypoint, not N)."""
    if len(candidates) == 0:
        return np.zeros((0, 2), np.int64)
    q, t = candidates[:, 0], candidates[:, 1]
    distances = hamming_distances(np.take(_as_words(query), q, axis=0), np.take(_as_words(train), t, axis=0))
    nearest_train, best, second = _nearest_per_row(q, t, distances, len(query), len(train))
    nearest_query, _, _ = _nearest_per_row(t, q, distances, len(train), len(query), with_second=False)
    rows = np.flatnonzero(nearest_train >= 0)
    columns = nearest_train[rows]
    keep = (best[rows] <= max_hamming) & ~(best[rows] >= ratio * second[rows]) & (nearest_query[columns] == rows)
    return np.stack([rows[keep], columns[keep]], axis=1).astype(np.int64)


def _camera_matrix(intrinsics: Intrinsics) -> np.ndarray:
    return np.array([[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy], [0.0, 0.0, 1.0]])


def _failed(matches: int, reason: str) -> RelativePose:
    return RelativePose(torch.eye(4, dtype=torch.float64), matches, 0, math.nan, False, reason)


def estimate_relative_pose(
    reference: FrameFeatures,
    current: FrameFeatures,
    intrinsics: Intrinsics,  # of the current frame's image
    options: FeatureOptions,
    T_rc_prior: torch.Tensor | None = None,  # [4, 4] motion-model guess of T_rc, or None
) -> RelativePose:
    """Pose of the current camera relative to the reference camera (module docstring, steps 2-3).

    With a prior, matching is first guided: a current keypoint may only match reference points whose
    projection at the prior lies within ``guided_radius`` of the image size (ORB-SLAM's search by
    projection; it keeps repeated texture from matching the wrong copy). When that finds no agreeing
    pose, the unguided match over the whole image decides, so a bad prior cannot hold the result.
    """
    if T_rc_prior is not None and options.guided_radius > 0:
        guided = _solve(reference, current, intrinsics, options,
                        guided_matches(reference, current, intrinsics, T_rc_prior, options))
        guided = _check_jump(guided, T_rc_prior, options)
        if guided.ok:
            return guided
    result = _solve(reference, current, intrinsics, options,
                    match_features(current.descriptors, reference.descriptors, options.ratio_test, options.max_hamming))
    return result if T_rc_prior is None else _check_jump(result, T_rc_prior, options)


def _check_jump(result: RelativePose, T_rc_prior: torch.Tensor, options: FeatureOptions) -> RelativePose:
    """Not trusted when the pose lies further from the prior than any hand-held motion between frames
    (a consensus of wrong matches on repeated texture)."""
    if not result.ok:
        return result
    delta = torch.linalg.inv(T_rc_prior.to(torch.float64)) @ result.T_rc
    cos = float(((delta[0, 0] + delta[1, 1] + delta[2, 2] - 1.0) / 2.0).clamp(-1.0, 1.0))
    if float(delta[:3, 3].norm()) > options.max_prior_jump_m or math.degrees(math.acos(cos)) > options.max_prior_jump_deg:
        return RelativePose(result.T_rc, result.matches, result.inliers, result.reprojection_px, False, "far_from_prior")
    return result


def _projections(reference: FrameFeatures, intrinsics: Intrinsics, T_rc: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The reference points in front of the current camera at ``T_rc``, projected into its image:
    ids [N'] int64 (rows of ``reference``) and pixels [N', 2] float64."""
    T_cr = np.linalg.inv(T_rc.detach().cpu().numpy().astype(np.float64))
    points = reference.points_c @ T_cr[:3, :3].T + T_cr[:3, 3]  # [N, 3] current camera (NaN rows stay NaN)
    z = points[:, 2]
    in_front = np.flatnonzero(np.isfinite(points).all(axis=1) & (z > 0))
    projected = np.stack([intrinsics.fx * points[in_front, 0] / z[in_front] + intrinsics.cx,
                          intrinsics.fy * points[in_front, 1] / z[in_front] + intrinsics.cy], axis=1)  # [N', 2] px
    return in_front.astype(np.int64), projected


def _projection_gate(reference: FrameFeatures, current: FrameFeatures, intrinsics: Intrinsics,
                     T_rc: torch.Tensor, radius: float) -> np.ndarray:
    """[P, 2] int64 pairs (current keypoint m, reference point n) that may match: n's projection at T_rc lies
    within the radius of m, from a k-d tree of the projections."""
    in_front, projected = _projections(reference, intrinsics, T_rc)
    if len(in_front) == 0 or len(current.keypoints) == 0:
        return np.zeros((0, 2), np.int64)
    limit = radius * max(intrinsics.width, intrinsics.height)
    pairs = cKDTree(np.asarray(current.keypoints, dtype=np.float64)).sparse_distance_matrix(
        cKDTree(projected), limit, output_type="ndarray")  # (i: keypoint, j: projection, v: distance <= limit)
    return np.stack([pairs["i"].astype(np.int64), in_front[pairs["j"]].astype(np.int64)], axis=1)


def guided_matches(reference: FrameFeatures, current: FrameFeatures, intrinsics: Intrinsics, T_rc: torch.Tensor,
                   options: FeatureOptions) -> np.ndarray:
    """ORB-SLAM's search by projection: :func:`match_features` of the current keypoints against the reference
    points whose projection at the prior ``T_rc`` [4, 4] lies within ``options.guided_radius`` of the image
    size.  -> [K, 2] int64 pairs (current keypoint, reference point), by keypoint.

    The compiled library's twin (mipslam/render/cpu/feature_match.h: a grid instead of a k-d tree, no
    candidate arrays: 4.6 -> 1.0 ms for a frame of fr1_rpy's 1000 keypoints) gives the same pairs as
    :func:`_projection_gate` + :func:`match_features`, the reference it is tested against, which runs where
    the library is not built.
    """
    library = compiled_library()
    if library is None:
        return match_features(current.descriptors, reference.descriptors, options.ratio_test, options.max_hamming,
                              _projection_gate(reference, current, intrinsics, T_rc, options.guided_radius))
    if len(current.descriptors) < 2 or len(reference.descriptors) < 2:
        return np.zeros((0, 2), np.int64)
    ids, projected = _projections(reference, intrinsics, T_rc)
    limit = options.guided_radius * max(intrinsics.width, intrinsics.height)
    return library.guided_match(current.keypoints, projected, ids, limit, current.descriptors,
                                reference.descriptors, options.ratio_test, options.max_hamming)


def _solve(reference: FrameFeatures, current: FrameFeatures, intrinsics: Intrinsics, options: FeatureOptions,
           pairs: np.ndarray) -> RelativePose:
    """PnP RANSAC on ``pairs`` [K, 2] (current keypoint, reference point) of the two frames' features."""
    if len(pairs):
        pairs = pairs[np.isfinite(reference.points_c[pairs[:, 1], 0])]
    if len(pairs) < max(6, options.min_inliers):
        return _failed(len(pairs), "too_few_matches")
    object_points = reference.points_c[pairs[:, 1]]  # [K, 3] reference camera
    image_points = current.keypoints[pairs[:, 0]].astype(np.float64)  # [K, 2] current image
    K = _camera_matrix(intrinsics)
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        object_points, image_points, K, None, iterationsCount=options.ransac_iterations,
        reprojectionError=options.ransac_reprojection_px, confidence=options.ransac_confidence,
        flags=cv2.SOLVEPNP_SQPNP)
    if not found or inliers is None or len(inliers) < 4:
        return _failed(len(pairs), "pnp_failed")
    inliers = inliers.reshape(-1)
    rvec, tvec = cv2.solvePnPRefineLM(object_points[inliers], image_points[inliers], K, None, rvec, tvec)
    projected, _ = cv2.projectPoints(object_points, rvec, tvec, K, None)
    errors = np.linalg.norm(projected.reshape(-1, 2) - image_points, axis=1)  # [K] px
    agree = errors < options.ransac_reprojection_px
    count = int(agree.sum())
    rms = float(np.sqrt(np.mean(errors[agree] ** 2))) if count else math.nan
    R, _ = cv2.Rodrigues(rvec)
    T_cr = np.eye(4)
    T_cr[:3, :3], T_cr[:3, 3] = R, tvec.reshape(3)
    T_rc = torch.from_numpy(np.linalg.inv(T_cr))
    if not np.isfinite(T_cr).all():
        return _failed(len(pairs), "pnp_failed")
    if count < options.min_inliers:
        return RelativePose(T_rc, len(pairs), count, rms, False, "too_few_inliers")
    if count < options.min_inlier_ratio * len(pairs):
        return RelativePose(T_rc, len(pairs), count, rms, False, "low_inlier_ratio")
    return RelativePose(T_rc, len(pairs), count, rms, True, "")


# ----------------------------------------------------------------------------- the tracking stage's front-end


@dataclass(frozen=True)
class FrontendStart:
    """Where tracking starts a frame from.

    T_wc: [4, 4] float64 camera-to-world start pose
    source: "features" (PnP against ``reference_index``), "motion_model" (features failed or are off)
        or "relocalised" (PnP against a keyframe after tracking failed)
    inliers: PnP inliers (0 for the motion model)
    reference_index: the frame the features were matched to (-1 for the motion model)
    reason: why the features were not used ("" when they were)
    """

    T_wc: torch.Tensor
    source: str
    inliers: int
    reference_index: int
    reason: str = ""


class Frontend:
    """Feature front-end of tracking: the ``frontend`` config section's method with the options' constants.

    ``cache_frames``: how many frames' features are kept (the previous frame and the keyframes tried
    for relocalisation); a miss recomputes them from the frame, which gives the same values.

    :meth:`detect_ahead` runs the image-only part (:func:`detect_keypoints`) for a frame read ahead, on the
    reader's thread while the frame loop works; :meth:`features` takes that detection where it was made on the
    very colour image it is asked about, and detects anew otherwise. Either way the values are the same.
    """

    # detections made ahead and not yet asked for (the frame loop reads one frame ahead)
    AHEAD_FRAMES = 4

    def __init__(self, config: FrontendConfig, options: FeatureOptions = FeatureOptions(), cache_frames: int = 32):
        self.config = config
        self.options = options
        self.cache_frames = max(2, cache_frames)
        self._features: OrderedDict[int, FrameFeatures] = OrderedDict()
        self._ahead: OrderedDict[int, tuple[torch.Tensor, Keypoints]] = OrderedDict()
        self._ahead_lock = threading.Lock()

    @staticmethod
    def motion_model(prediction: torch.Tensor, reason: str = "no_reference") -> FrontendStart:
        """The start when there is nothing to match: the motion model's prediction [4, 4]."""
        return FrontendStart(prediction, "motion_model", 0, -1, reason)

    @property
    def enabled(self) -> bool:
        return self.config.method != "none"

    def features(self, frame: Frame) -> FrameFeatures:
        """The frame's features, from the cache or computed now (keyed by ``frame.index``)."""
        return self.features_of(frame.index, lambda: frame)

    def features_of(self, index: int, read: Callable[[], Frame]) -> FrameFeatures:
        """Frame ``index``'s features, from the cache, or computed now on ``read()``: the frame is read only on a
        miss (reading a cached frame again may cost a resampling of its images, :class:`~mipslam.datasets.FrameCache`)."""
        cached = self._features.get(index)
        if cached is not None:
            self._features.move_to_end(index)
            return cached
        frame = read()
        with self._ahead_lock:
            ahead = self._ahead.pop(frame.index, None)
        # made on this very image (a frame re-timed since its read has another colour tensor)
        keypoints = ahead[1] if ahead is not None and ahead[0] is frame.color else detect_keypoints(frame.color,
                                                                                                   self.options)
        features = lift_keypoints(keypoints, frame.depth, frame.intrinsics, self.options)
        self._features[frame.index] = features
        while len(self._features) > self.cache_frames:
            self._features.popitem(last=False)
        return features

    def detect_ahead(self, frame: Frame) -> None:
        """Detect ``frame``'s keypoints now, for :meth:`features` to take later (any thread; the read-ahead's)."""
        if not self.enabled or frame.index in self._features:
            return
        keypoints = detect_keypoints(frame.color, self.options)
        with self._ahead_lock:
            self._ahead[frame.index] = (frame.color, keypoints)
            while len(self._ahead) > self.AHEAD_FRAMES:
                self._ahead.popitem(last=False)

    def start(
        self,
        frame: Frame,
        reference: Frame | None,  # the previous tracked frame (None: none)
        T_wc_reference: torch.Tensor | None,  # [4, 4] its current pose
        prediction: torch.Tensor,  # [4, 4] float64 motion-model pose of ``frame``
    ) -> FrontendStart:
        """The start pose of ``frame``: PnP against ``reference`` when the features agree, else ``prediction``."""
        return self.start_from(frame, None if reference is None else reference.index, lambda: reference,
                               T_wc_reference, prediction)

    def start_from(
        self,
        frame: Frame,
        reference_index: int | None,  # the previous tracked frame (None: none)
        read_reference: Callable[[], Frame],  # reads it, asked only where its features are not cached
        T_wc_reference: torch.Tensor | None,  # [4, 4] its current pose
        prediction: torch.Tensor,  # [4, 4] float64 motion-model pose of ``frame``
    ) -> FrontendStart:
        """:meth:`start` against frame ``reference_index``, read only where its features must be computed."""
        if not self.enabled or reference_index is None or T_wc_reference is None:
            return FrontendStart(prediction, "motion_model", 0, -1, "off" if not self.enabled else "no_reference")
        T_rc_prior = torch.linalg.inv(T_wc_reference.to(torch.float64)) @ prediction.to(torch.float64)
        relative = estimate_relative_pose(self.features_of(reference_index, read_reference), self.features(frame),
                                          frame.intrinsics, self.options, T_rc_prior)
        if not relative.ok:
            return FrontendStart(prediction, "motion_model", relative.inliers, -1, relative.reason)
        T_wc = T_wc_reference.to(torch.float64) @ relative.T_rc
        return FrontendStart(T_wc, "features", relative.inliers, reference_index)

    def relocalise(
        self,
        frame: Frame,
        keyframes: Sequence[tuple[Frame, torch.Tensor]],  # (keyframe's frame, its T_wc [4, 4]), newest first
        prediction: torch.Tensor | None = None,  # [4, 4] motion-model pose of ``frame`` (guides matching)
    ) -> FrontendStart | None:
        """PnP of ``frame`` against each keyframe; the start from the one with the most inliers, or None
        when no keyframe's features agree (the frame is lost)."""
        if not self.enabled:
            return None
        current = self.features(frame)
        best: FrontendStart | None = None
        for keyframe, T_wc_keyframe in keyframes[: self.options.relocalise_keyframes]:
            prior = None if prediction is None else torch.linalg.inv(T_wc_keyframe.to(torch.float64)) @ prediction
            relative = estimate_relative_pose(self.features(keyframe), current, frame.intrinsics, self.options, prior)
            if relative.ok and (best is None or relative.inliers > best.inliers):
                best = FrontendStart(T_wc_keyframe.to(torch.float64) @ relative.T_rc, "relocalised",
                                     relative.inliers, keyframe.index)
        return best

"""A DBoW2 vocabulary of ORB descriptors for the ORB-SLAM3 peer (ORB-SLAM3's ``ORBvoc.txt`` format).

ORB-SLAM3 needs a bag-of-words vocabulary for relocalisation, loop detection and some of its
matching; its own ``ORBvoc.txt`` is not distributed with any package. This trains one the way DBoW2's
``TemplatedVocabulary::create`` does (Galvez-Lopez and Tardos, IEEE T-RO 2012):

1. ORB descriptors (OpenCV, the extractor settings of ORB-SLAM3: 1000 features, 8 levels, scale 1.2)
   of every training image; 256-bit binary strings.
2. Hierarchical k-medians to depth ``levels``: the descriptors of a node are split into ``k`` clusters by
   k-majority (k-means++ seeding with Hamming distance; a cluster's centre is the bitwise majority of
   its members); a cluster with one descriptor, or at depth ``levels``, is a leaf, a *word*.
3. TF-IDF weights: word weight ``log(N / n_w)``, N training images, n_w images with a descriptor in w.

Text format (DBoW2 ``saveToTextFile``): a first line ``k L scoring weighting`` (scoring 0 = L1 norm,
weighting 0 = TF-IDF), then one line per node but the root, parents before children:
``parent_id is_leaf d_0 ... d_31 weight`` (descriptor bytes as integers, weight 0 for inner nodes).

Train it on images that are not in the sequence it will be evaluated on.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from mipslam.errors import MipslamError

__all__ = ["Vocabulary", "VocabularyReport", "collect_training_images", "hamming_distances", "orb_descriptors",
           "read_dbow2_header", "train_vocabulary", "train_vocabulary_file", "write_dbow2_text"]

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".ppm", ".bmp")
DESCRIPTOR_BYTES = 32  # ORB: 256 bits


# ----------------------------------------------------------------------------- training data

def collect_training_images(folders: Sequence[str | Path]) -> list[Path]:
    """8-bit images under ``folders`` (recursively), sorted; depth maps (a ``depth`` folder or name) left out.

    Raises MipslamError naming a folder that does not exist or holds no image."""
    found: list[Path] = []
    for folder in folders:
        folder = Path(folder).expanduser()
        if not folder.exists():
            raise MipslamError(f"{folder}: training image folder not found")
        files = [folder] if folder.is_file() else sorted(p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
        files = [p for p in files if "depth" not in p.name.lower() and "depth" not in p.parent.name.lower()]
        if not files:
            raise MipslamError(f"{folder}: no colour images (png/jpg) found for vocabulary training")
        found.extend(files)
    return found


def orb_descriptors(paths: Sequence[Path], features: int = 1000, scale_factor: float = 1.2, levels: int = 8
                    ) -> tuple[np.ndarray, np.ndarray]:
    """ORB descriptors of the 8-bit images ``paths``. -> (descriptors uint8 [N, 32], image index int64 [N]).

    16-bit images (depth) are skipped; an unreadable file raises MipslamError naming it."""
    import cv2

    orb = cv2.ORB_create(nfeatures=features, scaleFactor=scale_factor, nlevels=levels, edgeThreshold=19,
                         patchSize=31, fastThreshold=20)
    chunks, owners = [], []
    for index, path in enumerate(paths):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise MipslamError(f"{path}: cannot read this image")
        if image.dtype != np.uint8:
            continue
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        _keypoints, descriptors = orb.detectAndCompute(image, None)
        if descriptors is None:
            continue
        chunks.append(descriptors)
        owners.append(np.full(len(descriptors), index, dtype=np.int64))
    if not chunks:
        raise MipslamError("no ORB features found in the training images; give textured 8-bit colour images")
    return np.concatenate(chunks), np.concatenate(owners)


# ----------------------------------------------------------------------------- k-majority

def hamming_distances(descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Hamming distances between binary descriptors. descriptors uint8 [N, 32], centres uint8 [K, 32] -> int [N, K]."""
    a = np.ascontiguousarray(descriptors).view(np.uint64)  # [N, 4]
    b = np.ascontiguousarray(centres).view(np.uint64)  # [K, 4]
    return np.bitwise_count(a[:, None, :] ^ b[None, :, :]).sum(axis=2, dtype=np.int64)


def _majority(descriptors: np.ndarray) -> np.ndarray:
    """Bitwise majority of binary descriptors [M, 32] -> [32] (a bit is set when at least half the members set it)."""
    bits = np.unpackbits(descriptors, axis=1)  # [M, 256]
    return np.packbits(2 * bits.sum(axis=0, dtype=np.int64) >= len(descriptors))


def _seed_centres(descriptors: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding (Arthur and Vassilvitskii, 2007) with Hamming distance: -> indices of k descriptors."""
    chosen = [int(rng.integers(len(descriptors)))]
    nearest = hamming_distances(descriptors, descriptors[chosen]).ravel().astype(np.float64)
    while len(chosen) < k:
        weights = nearest ** 2
        total = weights.sum()
        if total <= 0:  # every descriptor equals a chosen centre
            break
        pick = int(rng.choice(len(descriptors), p=weights / total))
        chosen.append(pick)
        nearest = np.minimum(nearest, hamming_distances(descriptors, descriptors[[pick]]).ravel())
    return np.asarray(chosen)


def _k_majority(descriptors: np.ndarray, k: int, rng: np.random.Generator, iterations: int) -> list[np.ndarray]:
    """Split ``descriptors`` [M, 32] into at most k clusters; -> member index arrays (non-empty)."""
    if len(descriptors) <= k:
        return [np.array([i]) for i in range(len(descriptors))]
    centres = descriptors[_seed_centres(descriptors, k, rng)]
    labels = None
    for _ in range(iterations):
        new_labels = hamming_distances(descriptors, centres).argmin(axis=1)
        if labels is not None and np.array_equal(new_labels, labels):
            break
        labels = new_labels
        centres = np.stack([_majority(descriptors[labels == j]) if np.any(labels == j) else centres[j]
                            for j in range(len(centres))])
    return [members for j in range(len(centres)) if len(members := np.flatnonzero(labels == j))]


# ----------------------------------------------------------------------------- tree

@dataclass(frozen=True)
class Vocabulary:
    """A DBoW2 tree. Node 0 is the root; node i > 0 has parents[i] < i. descriptors uint8 [nodes, 32];
    leaf bool [nodes]; weights float64 [nodes] (idf of the words, 0 for inner nodes)."""

    k: int
    levels: int
    parents: np.ndarray
    descriptors: np.ndarray
    leaf: np.ndarray
    weights: np.ndarray

    @property
    def words(self) -> int:
        return int(self.leaf.sum())


def train_vocabulary(descriptors: np.ndarray, image_index: np.ndarray, k: int = 10, levels: int = 5, seed: int = 0,
                     iterations: int = 10) -> Vocabulary:
    """Hierarchical k-medians tree with TF-IDF word weights (see the module docstring).

    descriptors uint8 [N, 32]; image_index int [N]: the training image of each descriptor."""
    if k < 2 or levels < 1:
        raise MipslamError(f"vocabulary k={k}, levels={levels}: need k >= 2 and levels >= 1")
    descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8)
    if descriptors.ndim != 2 or descriptors.shape[1] != DESCRIPTOR_BYTES or len(descriptors) == 0:
        raise MipslamError(f"vocabulary training needs ORB descriptors [N, 32], got {list(descriptors.shape)}")
    rng = np.random.default_rng(seed)
    parents, centres, is_leaf, members_of = [0], [np.zeros(DESCRIPTOR_BYTES, np.uint8)], [False], [None]
    queue = [(0, np.arange(len(descriptors)), 0)]  # (node, member indices, depth), breadth first
    while queue:
        next_queue = []
        for node, members, depth in queue:
            for cluster in _k_majority(descriptors[members], k, rng, iterations):
                child_members = members[cluster]
                child = len(parents)
                parents.append(node)
                centres.append(_majority(descriptors[child_members]))
                leaf = depth + 1 >= levels or len(child_members) == 1
                is_leaf.append(leaf)
                members_of.append(child_members if leaf else None)
                if not leaf:
                    next_queue.append((child, child_members, depth + 1))
        queue = next_queue
    images = int(image_index.max()) + 1 if len(image_index) else 0
    weights = np.zeros(len(parents))
    for node, members in enumerate(members_of):
        if members is not None:
            with_word = len(np.unique(image_index[members]))
            weights[node] = math.log(images / with_word) if with_word else 0.0
    return Vocabulary(k, levels, np.asarray(parents, np.int64), np.stack(centres), np.asarray(is_leaf), weights)


def write_dbow2_text(path: str | Path, vocabulary: Vocabulary) -> Path:
    """Write ``vocabulary`` in DBoW2's text format (ORB-SLAM3 ``ORBvoc.txt``), atomically."""
    from mipslam.io.run_folder import write_text_atomic

    lines = [f"{vocabulary.k} {vocabulary.levels} 0 0"]
    for node in range(1, len(vocabulary.parents)):
        weight = f"{vocabulary.weights[node]:.6g}" if vocabulary.leaf[node] else "0"
        descriptor = " ".join(str(int(b)) for b in vocabulary.descriptors[node])
        lines.append(f"{vocabulary.parents[node]} {int(vocabulary.leaf[node])} {descriptor} {weight}")
    return write_text_atomic(Path(path), "\n".join(lines))


def read_dbow2_header(path: str | Path) -> dict[str, int]:
    """``k``, ``levels``, ``nodes`` and ``words`` of a DBoW2 text vocabulary (checks every line's shape)."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise MipslamError(f"{path}: cannot read the vocabulary ({exc})") from None
    head = lines[0].split() if lines else []
    if len(head) != 4:
        raise MipslamError(f"{path}:1: expected 'k L scoring weighting'")
    words = 0
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split()
        if len(fields) != 3 + DESCRIPTOR_BYTES or int(fields[0]) >= number - 1:
            raise MipslamError(f"{path}:{number}: expected 'parent is_leaf 32 bytes weight' with an earlier parent")
        words += int(fields[1])
    return {"k": int(head[0]), "levels": int(head[1]), "nodes": len(lines) - 1, "words": words}


# ----------------------------------------------------------------------------- one call

@dataclass(frozen=True)
class VocabularyReport:
    path: Path
    images: int
    descriptors: int
    nodes: int
    words: int
    k: int
    levels: int
    seconds: float
    sources: tuple[str, ...]

    def describe(self) -> str:
        return (f"vocabulary {self.path}: k={self.k}, L={self.levels}, {self.words} words ({self.nodes} nodes) from "
                f"{self.descriptors} ORB descriptors of {self.images} images in {self.seconds:.1f} s; trained on: "
                f"{', '.join(self.sources)} (evaluate ORB-SLAM3 only on sequences not among them)")


def train_vocabulary_file(folders: Sequence[str | Path], out: str | Path, k: int = 10, levels: int = 5,
                          max_images: int = 0, seed: int = 0) -> VocabularyReport:
    """Collect images, extract ORB descriptors, train, write ``out``; max_images > 0 takes that many, evenly spaced."""
    start = time.perf_counter()
    paths = collect_training_images(folders)
    if max_images and len(paths) > max_images:
        paths = [paths[i] for i in np.linspace(0, len(paths) - 1, max_images).round().astype(int)]
    descriptors, owners = orb_descriptors(paths)
    log.info("vocabulary: %d descriptors from %d images; clustering k=%d L=%d", len(descriptors), len(paths), k, levels)
    vocabulary = train_vocabulary(descriptors, owners, k=k, levels=levels, seed=seed)
    path = write_dbow2_text(out, vocabulary)
    return VocabularyReport(path, len(paths), len(descriptors), len(vocabulary.parents) - 1, vocabulary.words, k, levels,
                            time.perf_counter() - start, tuple(str(Path(f).expanduser().resolve()) for f in folders))

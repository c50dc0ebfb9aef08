"""Mid-360 chunk clustering: DBSCAN, component merging, background removal, UAV selection by density.

The AAUTE paper's steps 2-5 (``reference/mmaud_and_teacher.md`` section 3.1 [B]) on the points of
one chunk of 20 consecutive scans:

1. DBSCAN (eps 1.0 m, min_samples 10) on the xyz of the whole chunk (the frame index is not a
   coordinate, as in Deng et al., section 3.2);
2. clusters whose nearest points are closer than 2.5 m are merged (connected components of the
   "closer than" graph; single linkage, because a moving drone's 2 s track is elongated and
   centroid distances would split it); components under 20 points are dropped;
3. the largest and the smallest component are dropped (background and partial background);
4. the UAV component is the one of highest density (:func:`cluster_density`).

Robustness additions (this project; see :func:`extract_uav`): with the static-background map of
:mod:`datamodules.teacher.background`, the steps run on the non-static returns, components that
mostly touch static structure are rejected, and "drop largest and smallest" (whose target, the
background, is then already gone) is not applied; candidates must be seen in two scans and be
no wider than a drone in any scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from sklearn.cluster import DBSCAN

from datamodules.teacher.background import voxel_keys


def dbscan(points: np.ndarray, eps: float = 1.0, min_samples: int = 10, cube_m: float = 0.25) -> np.ndarray:
    """scikit-learn DBSCAN labels (-1 = noise) of ``points``.

    Returns that share a cube of side ``cube_m`` enter DBSCAN as one sample at their centroid,
    weighted by their number (DBSCAN's ``sample_weight``): densities are kept, distances change by
    at most the cube's diagonal (0.43 m for 0.25 m cubes, under half of eps), and the cost grows
    with the occupied space instead of the points (a close drone returns hundreds of points per
    scan, all within eps of each other, which makes DBSCAN's neighbour lists quadratic).
    ``cube_m`` = 0 runs DBSCAN on the points themselves.
    """
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    model = DBSCAN(eps=eps, min_samples=min_samples, algorithm="kd_tree")
    if cube_m <= 0:
        return model.fit_predict(points).astype(np.int64)
    codes, cubes = pd.factorize(voxel_keys(points, cube_m))
    counts = np.bincount(codes)
    if counts.size == n:
        return model.fit_predict(points).astype(np.int64)
    centres = np.stack([np.bincount(codes, weights=points[:, k]) for k in range(3)], axis=1) / counts[:, None]
    return model.fit_predict(centres, sample_weight=counts.astype(np.float64)).astype(np.int64)[codes]


def _close_cluster_pairs(points: np.ndarray, cluster: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of clusters whose nearest points are closer than ``distance`` (exact).

    Each cluster is first summarised by the centroids of its occupied cubes of side ``distance / 2``
    (every point lies within a cube diagonal of its centroid); cube pairs of different clusters
    within ``distance`` plus two diagonals are candidates, checked point to point with a KD-tree.
    A pair search among all points would be quadratic in dense clusters (a close wall holds
    thousands of returns within 2.5 m of each other).
    """
    cube = distance / 2.0
    keys = voxel_keys(points, cube)
    order = np.lexsort((keys, cluster))
    sorted_keys, sorted_cluster = keys[order], cluster[order]
    changes = (sorted_keys[1:] != sorted_keys[:-1]) | (sorted_cluster[1:] != sorted_cluster[:-1])
    first = np.concatenate([[True], changes])
    group = np.cumsum(first) - 1
    counts = np.bincount(group)
    reps = np.stack([np.bincount(group, weights=points[order, k]) for k in range(3)], axis=1) / counts[:, None]
    rep_cluster = sorted_cluster[first]
    pairs = cKDTree(reps).query_pairs(distance + 2.0 * np.sqrt(3.0) * cube, output_type="ndarray")
    ca, cb = rep_cluster[pairs[:, 0]], rep_cluster[pairs[:, 1]]
    between = ca != cb
    if not between.any():
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    candidates = np.unique(np.sort(np.stack([ca[between], cb[between]], axis=1), axis=1), axis=0)
    sizes = np.bincount(cluster)
    trees: dict[int, cKDTree] = {}
    close = []
    for i, j in candidates:
        small, large = (int(i), int(j)) if sizes[i] <= sizes[j] else (int(j), int(i))
        if large not in trees:
            trees[large] = cKDTree(points[cluster == large])
        nearest, _ = trees[large].query(points[cluster == small], distance_upper_bound=distance)
        close.append(bool(np.isfinite(nearest).any()))
    close = np.asarray(close, dtype=bool)
    return candidates[close, 0].astype(np.int64), candidates[close, 1].astype(np.int64)


def merge_clusters(points: np.ndarray, labels: np.ndarray, merge_distance: float = 2.5,
                   min_size: float = 20, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Merge clusters whose nearest points are within ``merge_distance``; drop small components.

    Args:
        points: N x 3.
        labels: DBSCAN labels (-1 = noise).
        merge_distance: clusters closer than this (m) join one component [B: 2.5 m].
        min_size: components with fewer (weighted) points are dropped [B: 20].
        weights: points each sample stands for (1 if None).

    Returns:
        Component label per point (-1 for noise and dropped components, components numbered from
        0) and the (weighted) size of each component.
    """
    weights = np.ones(points.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    clustered = np.flatnonzero(labels >= 0)
    out = np.full(points.shape[0], -1, dtype=np.int64)
    if clustered.size == 0:
        return out, np.zeros(0)
    _, cluster = np.unique(labels[clustered], return_inverse=True)
    n_clusters = int(cluster.max()) + 1
    if n_clusters > 1:
        a, b = _close_cluster_pairs(points[clustered], cluster, merge_distance)
        graph = coo_matrix((np.ones(a.size), (a, b)), shape=(n_clusters, n_clusters))
        _, component_of = connected_components(graph, directed=False)
    else:
        component_of = np.zeros(1, dtype=np.int64)
    component = component_of[cluster]
    sizes = np.bincount(component, weights=weights[clustered])
    kept = np.flatnonzero(sizes >= min_size)
    renumber = np.full(sizes.size, -1, dtype=np.int64)
    renumber[kept] = np.arange(kept.size)
    out[clustered] = renumber[component]
    return out, sizes[kept]


def drop_largest_and_smallest(sizes: np.ndarray, min_components: int = 3) -> np.ndarray:
    """The paper's background rule: drop the largest and the smallest component [B].

    Args:
        sizes: point count per component.
        min_components: the rule applies only with at least this many components; with one or two
            it would drop everything, drone included [P].

    Returns:
        Boolean keep mask per component.
    """
    keep = np.ones(sizes.size, dtype=bool)
    if sizes.size >= min_components:
        keep[int(np.argmax(sizes))] = False
        keep[int(np.argmin(sizes))] = False
    return keep


def cluster_density(points: np.ndarray, voxel_m: float = 0.5) -> float:
    """Returns per m^3 of occupied space: points / (occupied cubes of side ``voxel_m`` x voxel_m^3).

    Liang et al.'s density (points over occupied voxel volume, ``reference/mmaud_and_teacher.md``
    section 3.3), computed over the chunk's accumulation of 20 scans. A drone's returns pile up on
    a body smaller than a cube and its 2 s path crosses few cubes, so several returns share each
    cube; what survives static-background removal otherwise (edges of far surfaces hit now and
    then, swaying vegetation) spreads one return per cube. The cube is 0.5 m, the size of a small
    drone (DJI Avata 0.18 x 0.18 m to M300 0.81 m); Liang's 0.2 m cube holds about one return per
    cube for drones and clutter alike at the Mid-360's sparse sampling.
    """
    if points.shape[0] == 0:
        return 0.0
    occupied = np.unique(voxel_keys(points, voxel_m)).size
    return float(points.shape[0] / (occupied * voxel_m**3))


def frame_extent(points: np.ndarray, frame_index: np.ndarray) -> float:
    """Largest bounding-box diagonal of the returns of one scan (m)."""
    extent = 0.0
    for j in np.unique(frame_index):
        p = points[frame_index == j]
        extent = max(extent, float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))))
    return extent


def static_contact(component: np.ndarray, static_points: np.ndarray, contact_m: float) -> float:
    """Share of a component's returns that lie within ``contact_m`` of a static return."""
    if static_points.shape[0] == 0 or component.shape[0] == 0:
        return 0.0
    lo, hi = component.min(axis=0) - contact_m, component.max(axis=0) + contact_m
    nearby = static_points[np.all((static_points >= lo) & (static_points <= hi), axis=1)]
    if nearby.shape[0] == 0:
        return 0.0
    distance, _ = cKDTree(nearby).query(component, distance_upper_bound=contact_m)
    return float(np.isfinite(distance).mean())


@dataclass
class ChunkResult:
    """What clustering found in one chunk (for diagnostics and tests)."""

    n_points: int
    n_dynamic: int
    n_components: int = 0
    n_candidates: int = 0
    chosen_size: int = 0
    chosen_density: float = 0.0
    static_known: bool = False


def extract_uav(
    points: np.ndarray,
    frame_index: np.ndarray,
    static: np.ndarray | None,
    *,
    eps: float = 1.0,
    min_samples: int = 10,
    cube_m: float = 0.25,
    merge_distance: float = 2.5,
    min_component_size: int = 20,
    drop_extremes: bool = True,
    drop_extremes_min_components: int = 3,
    contact_m: float = 0.3,
    max_contact_share: float = 0.5,
    density_voxel_m: float = 0.5,
    min_frames: int = 2,
    max_frame_extent_m: float = 2.0,
    min_density: float = 0.0,
) -> tuple[np.ndarray, ChunkResult]:
    """The chunk's UAV returns: a boolean mask over ``points`` (all False when there is no UAV).

    Without a static map (``static`` None) the paper's steps run literally on every return:
    DBSCAN, merge, drop the largest and the smallest component, highest density. With a static
    map (this project's default) the background those heuristics aim at is known explicitly, so:
    DBSCAN and merging run on the non-static returns only; a component most of whose returns
    touch static returns (within ``contact_m``) is rejected (the fringe of a structure whose cubes
    fell just short of the static threshold, or a drone pressed against a wall: ambiguous);
    "drop largest and smallest" is not applied, because among moving returns the largest
    component is usually the drone itself. In both modes a UAV candidate must be seen in
    ``min_frames`` scans and no scan may spread its returns wider than ``max_frame_extent_m``.

    Args:
        points: the chunk's returns (N x 3, metres).
        frame_index: scan of each return within the chunk.
        static: per-point static-background flag, or None.
        eps, min_samples: DBSCAN [B: 1.0 m, 10].
        cube_m: returns sharing a cube this size are one weighted DBSCAN sample (:func:`dbscan`) [P].
        merge_distance, min_component_size: component merging [B: 2.5 m, 20 points].
        drop_extremes: apply the paper's "drop largest and smallest" without a static map [B].
        drop_extremes_min_components: ... only with at least this many components (with fewer
            it would drop everything) [P].
        contact_m: a return this close to a static return touches static structure: range and
            angle noise (2 cm, 0.15 degrees: 5 cm at 20 m) plus the gaps of a surface's sampling [P].
        max_contact_share: a candidate with a larger share of touching returns is the fringe of a
            static structure, not a drone (a drone flying 0.5 m from a wall is still kept) [P].
        density_voxel_m: cube of :func:`cluster_density` [P].
        min_frames: scans of the chunk a candidate must have returns in (a burst within one
            scan is a transient: a glint, a bird crossing) [P].
        max_frame_extent_m: widest spread of one scan's returns of a candidate: the largest MMAUD
            drone (DJI M300, 0.81 x 0.67 x 0.43 m, diagonal 1.15 m) plus 0.1 s of flight at 5 m/s
            and noise; rejects cars, trees and walls that move or appear [P].
        min_density: candidates below this density (returns per m^3) are rejected (0 = off) [P].

    Returns:
        The mask of the chosen component's returns, and a :class:`ChunkResult`.
    """
    n = points.shape[0]
    chosen = np.zeros(n, dtype=bool)
    dynamic = np.ones(n, dtype=bool) if static is None else ~static
    result = ChunkResult(n_points=n, n_dynamic=int(dynamic.sum()), static_known=static is not None)
    if result.n_dynamic < max(min_samples, min_component_size):
        return chosen, result
    dyn_index = np.flatnonzero(dynamic)
    labels = dbscan(points[dyn_index], eps, min_samples, cube_m)  # step 1
    component, sizes = merge_clusters(points[dyn_index], labels, merge_distance, min_component_size)  # step 2
    result.n_components = int(sizes.size)
    if sizes.size == 0:
        return chosen, result
    paper_rule = static is None and drop_extremes  # step 3, only without a static map
    keep = drop_largest_and_smallest(sizes, drop_extremes_min_components) if paper_rule else np.ones(sizes.size, bool)
    candidates = _uav_candidates(points, frame_index, [dyn_index[component == c] for c in np.flatnonzero(keep)],
                                 None if static is None else points[~dynamic], min_frames, max_frame_extent_m,
                                 density_voxel_m, min_density, contact_m, max_contact_share)
    result.n_candidates = len(candidates)
    if candidates:
        members, result.chosen_density = _densest(candidates)  # step 4
        chosen[members] = True
        result.chosen_size = int(chosen.sum())
    return chosen, result


def _uav_candidates(
    points: np.ndarray,
    frame_index: np.ndarray,
    components: list[np.ndarray],
    static_points: np.ndarray | None,
    min_frames: int,
    max_frame_extent_m: float,
    density_voxel_m: float,
    min_density: float,
    contact_m: float,
    max_contact_share: float,
) -> list[tuple[np.ndarray, float]]:
    """The components (indices into ``points``) that pass the UAV checks of :func:`extract_uav`, with their density.

    A candidate is seen in ``min_frames`` scans, no scan spreads its returns wider than
    ``max_frame_extent_m``, its density is at least ``min_density``, and (with a static map) at
    most ``max_contact_share`` of its returns touch static returns.
    """
    candidates = []
    for members in components:
        if np.unique(frame_index[members]).size < min_frames:
            continue
        if frame_extent(points[members], frame_index[members]) > max_frame_extent_m:
            continue
        density = cluster_density(points[members], density_voxel_m)
        if density < min_density:
            continue
        if static_points is not None and static_contact(points[members], static_points, contact_m) > max_contact_share:
            continue
        candidates.append((members, density))
    return candidates


def _densest(candidates: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, float]:
    """The paper's UAV choice: the candidate of highest density (the first one on a tie)."""
    best, best_density = candidates[0][0], -np.inf
    for members, density in candidates:
        if density > best_density:
            best, best_density = members, density
    return best, float(best_density)

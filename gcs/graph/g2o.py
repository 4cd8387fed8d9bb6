"""g2o 2D pose-graph files: import, export, lossless merging of repeated edges.

Format (one record a line; ``#`` starts a comment)::

    VERTEX_SE2 id x y theta
    EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33
    FIX id

The information matrix is given in g2o's upper-triangular order (xx xy xth yy yth thth); the
tangent order ``(x, y, theta)`` is GTSAM's ``Pose2`` order. A malformed line raises
:class:`G2oError` naming the line number and what is wrong.

Repeated edges between the same two vertices are merged into one losslessly (paper 4.7:
Gaussian edges between the same nodes add their information): the merged measurement is the
information-weighted mean on the manifold, its information the sum. The constant part of the
chi2 that the merge removes (the disagreement of the repeated measurements among themselves)
is kept in ``chi2_offset`` so that chi2 values stay comparable with the original graph.

Initial estimates (:func:`initial_poses`): the file's vertices, chained odometry (edges
``i -> i+1``) or the minimum-uncertainty spanning tree over all edges (paper 4.6). A graph whose
odometry chain has a gap, or whose file lacks some vertices, falls back to the spanning tree and
says so. Every connected component (an isolated vertex is one) is anchored on its smallest id:
:func:`to_gtsam` puts a prior there, so a graph in pieces solves without a singular system.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import gtsam
import numpy as np
from numpy.typing import NDArray

from gcs.graph import se2
from gcs.graph.pose2_gauss_newton import Pose2Factors
from gcs.graph.spanning_tree_init import component_labels, spanning_tree_from_factors

__all__ = [
    "G2oError",
    "G2oGraph",
    "G2oStart",
    "StartKind",
    "chained_odometry",
    "component_roots",
    "initial_poses",
    "merge_repeated_edges",
    "parse_g2o",
    "read_g2o",
    "to_gtsam",
    "write_g2o",
]

FloatArray = NDArray[np.floating[Any]]
IntArray = NDArray[np.int64]


class G2oError(ValueError):
    """A g2o file or graph is malformed; the message names the line (or edge) at fault."""


@dataclass(frozen=True)
class G2oGraph:
    """A 2D pose graph as arrays.

    ``vertex_ids`` (N,) with ``vertex_poses`` (N, 3) in the file's frame; ``edge_ij`` (M, 2)
    vertex ids; ``edge_z`` (M, 3) measured ``i_from_j`` poses; ``edge_info`` (M, 3, 3)
    information matrices; ``fixed`` ids from ``FIX`` lines; ``edge_lines`` (M,) source line
    numbers (0 when not read from a file); ``chi2_offset`` the constant removed by merging.
    """

    vertex_ids: IntArray
    vertex_poses: FloatArray
    edge_ij: IntArray
    edge_z: FloatArray
    edge_info: FloatArray
    fixed: tuple[int, ...] = ()
    edge_lines: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    chi2_offset: float = 0.0

    @property
    def node_ids(self) -> IntArray:
        """Sorted ids of every vertex declared or referenced by an edge."""
        return np.union1d(self.vertex_ids, self.edge_ij.ravel()).astype(np.int64)

    def chi2(self, poses_by_id: dict[int, FloatArray] | gtsam.Values) -> float:
        """``sum e' Omega e`` (GTSAM ``BetweenFactorPose2`` residuals) plus ``chi2_offset``."""
        graph, _ = to_gtsam(self, prior_sigma=None, poses=np.zeros((self.node_ids.size, 3)))
        values = poses_by_id if isinstance(poses_by_id, gtsam.Values) else _values(poses_by_id)
        return 2.0 * graph.error(values) + self.chi2_offset


def _values(poses_by_id: dict[int, FloatArray]) -> gtsam.Values:
    values = gtsam.Values()
    for key, p in poses_by_id.items():
        values.insert(int(key), se2.pose2(p))
    return values


_EDGE_NUMBERS = 11


def _floats(tokens: list[str], lineno: int, tag: str) -> list[float]:
    try:
        out = [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise G2oError(f"g2o line {lineno}: {tag}: {bad!r} is not a number") from None
    for t, v in zip(tokens, out, strict=True):
        if not math.isfinite(v):
            raise G2oError(f"g2o line {lineno}: {tag}: non-finite value {t!r}")
    return out


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


def _vertex_id(token: str, lineno: int, tag: str) -> int:
    try:
        vid = int(token)
    except ValueError:
        raise G2oError(f"g2o line {lineno}: {tag}: vertex id {token!r} is not an integer") from None
    if not 0 <= vid < 2**63:
        raise G2oError(f"g2o line {lineno}: {tag}: vertex id {vid} is outside 0 .. 2^63-1")
    return vid


def info_from_upper(u: FloatArray) -> FloatArray:
    """3x3 symmetric information from g2o's ``I11 I12 I13 I22 I23 I33``."""
    return np.array([[u[0], u[1], u[2]], [u[1], u[3], u[4]], [u[2], u[4], u[5]]])


def _check_info(info: FloatArray, where: str) -> None:
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(info)
        raise G2oError(
            f"{where}: information matrix is not positive definite (eigenvalues {eig.tolist()})"
        ) from None


def parse_g2o(text: str, *, merge_repeated: bool = True) -> G2oGraph:
    """Parse g2o text. Raises :class:`G2oError` naming the line of the first problem.

    With ``merge_repeated`` (the default) repeated edges are merged (see module docstring).
    """
    vids: list[int] = []
    vposes: list[list[float]] = []
    seen: dict[int, int] = {}
    eij: list[tuple[int, int]] = []
    ez: list[list[float]] = []
    einfo: list[FloatArray] = []
    elines: list[int] = []
    fixed: list[int] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        tokens = line.split()
        tag = tokens[0]
        args = tokens[1:]
        if tag == "VERTEX_SE2":
            if len(args) != 4:
                raise G2oError(f"g2o line {lineno}: VERTEX_SE2 expects 4 numbers, got {len(args)}")
            vid = _vertex_id(args[0], lineno, tag)
            if vid in seen:
                raise G2oError(
                    f"g2o line {lineno}: VERTEX_SE2 {vid} already defined on line {seen[vid]}"
                )
            seen[vid] = lineno
            vids.append(vid)
            vposes.append(_floats(args[1:], lineno, tag))
        elif tag == "EDGE_SE2":
            if len(args) != _EDGE_NUMBERS:
                raise G2oError(
                    f"g2o line {lineno}: EDGE_SE2 expects {_EDGE_NUMBERS} numbers, got {len(args)}"
                )
            i = _vertex_id(args[0], lineno, tag)
            j = _vertex_id(args[1], lineno, tag)
            if i == j:
                raise G2oError(f"g2o line {lineno}: EDGE_SE2 connects vertex {i} to itself")
            nums = _floats(args[2:], lineno, tag)
            info = info_from_upper(np.array(nums[3:]))
            _check_info(info, f"g2o line {lineno}: EDGE_SE2 {i} {j}")
            eij.append((i, j))
            ez.append(nums[:3])
            einfo.append(info)
            elines.append(lineno)
        elif tag == "FIX":
            if len(args) != 1:
                raise G2oError(f"g2o line {lineno}: FIX expects 1 vertex id, got {len(args)}")
            fixed.append(_vertex_id(args[0], lineno, tag))
        else:
            raise G2oError(
                f"g2o line {lineno}: unsupported record {tag!r} "
                "(expected VERTEX_SE2, EDGE_SE2 or FIX)"
            )
    if not vids and not eij:
        raise G2oError("g2o text has no VERTEX_SE2 or EDGE_SE2 record")
    graph = G2oGraph(
        vertex_ids=np.array(vids, dtype=np.int64),
        vertex_poses=np.array(vposes, dtype=float).reshape(-1, 3),
        edge_ij=np.array(eij, dtype=np.int64).reshape(-1, 2),
        edge_z=np.array(ez, dtype=float).reshape(-1, 3),
        edge_info=np.array(einfo, dtype=float).reshape(-1, 3, 3),
        fixed=tuple(fixed),
        edge_lines=np.array(elines, dtype=np.int64),
    )
    return merge_repeated_edges(graph) if merge_repeated else graph


def read_g2o(path: str | Path, *, merge_repeated: bool = True) -> G2oGraph:
    """Read a g2o file; errors name the file and the line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise G2oError(f"{path}: cannot read: {err.strerror or err}") from None
    try:
        return parse_g2o(text, merge_repeated=merge_repeated)
    except G2oError as err:
        raise G2oError(f"{path}: {err}") from None


def merge_gaussian_edges(
    zs_a_from_b: FloatArray, infos: FloatArray, *, iterations: int = 5
) -> tuple[FloatArray, FloatArray, float]:
    """Merge K measurements of the same ``a_from_b`` (K, 3) with informations (K, 3, 3).

    Returns ``(z, info, chi2_offset)``: the information-weighted manifold mean (Gauss-Newton on
    ``sum ||Log(z^-1 z_k)||^2_{info_k}``), the summed information and the residual sum at the
    mean, which is the part of the chi2 the single merged edge no longer carries.
    """
    info_sum = infos.sum(axis=0)
    z = se2.weighted_mean(zs_a_from_b, infos, iterations=iterations, tol=1e-14)
    poses = [se2.pose2(zk) for zk in zs_a_from_b]
    offset = 0.0
    for pk, ik in zip(poses, infos, strict=True):
        r = gtsam.Pose2.Logmap(z.between(pk))
        offset += float(r @ ik @ r)
    return se2.pose_vec(z), info_sum, offset


def reverse_edge(z_a_from_b: FloatArray, info: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The same constraint stated as ``b_from_a``: ``z^-1`` with information ``Ad^T info Ad``.

    With right perturbations ``x_b = x_a z Exp(n)`` gives ``x_a = x_b z^-1 Exp(-Ad_z n)``: the
    covariance becomes ``Ad_z C Ad_z'``, so the information becomes ``Ad_{z^-1}' I Ad_{z^-1}``.
    """
    ad = se2.adjoint(se2.inverse(z_a_from_b))
    return se2.inverse(z_a_from_b), ad.T @ info @ ad


def merge_repeated_edges(graph: G2oGraph) -> G2oGraph:
    """Merge edges between the same pair of vertices (either direction) into one edge each.

    The first occurrence fixes the merged edge's position, direction and source line.
    """
    groups: dict[tuple[int, int], list[int]] = {}
    for m, (i, j) in enumerate(graph.edge_ij.tolist()):
        groups.setdefault((min(i, j), max(i, j)), []).append(m)
    if all(len(g) == 1 for g in groups.values()):
        return graph
    keep: list[int] = []
    zs = graph.edge_z.copy()
    infos = graph.edge_info.copy()
    offset = graph.chi2_offset
    for members in groups.values():
        first = members[0]
        keep.append(first)
        if len(members) == 1:
            continue
        i0, j0 = graph.edge_ij[first]
        mz, mi = [], []
        for m in members:
            z, info = graph.edge_z[m], graph.edge_info[m]
            if graph.edge_ij[m, 0] != i0:
                z, info = reverse_edge(z, info)
            mz.append(z)
            mi.append(info)
        z, info, extra = merge_gaussian_edges(np.array(mz), np.array(mi))
        zs[first], infos[first] = z, info
        offset += extra
    keep.sort()
    idx = np.array(keep, dtype=np.int64)
    lines = graph.edge_lines[idx] if graph.edge_lines.size else graph.edge_lines
    return G2oGraph(
        vertex_ids=graph.vertex_ids,
        vertex_poses=graph.vertex_poses,
        edge_ij=graph.edge_ij[idx],
        edge_z=zs[idx],
        edge_info=infos[idx],
        fixed=graph.fixed,
        edge_lines=lines,
        chi2_offset=offset,
    )


def _fmt(v: float) -> str:
    return repr(float(v))


def write_g2o(path: str | Path, graph: G2oGraph, *, merge_repeated: bool = True) -> None:
    """Write ``graph`` as g2o text (full float precision, repeated edges merged by default)."""
    if merge_repeated:
        graph = merge_repeated_edges(graph)
    lines = []
    for vid, p in zip(graph.vertex_ids.tolist(), graph.vertex_poses, strict=True):
        lines.append(f"VERTEX_SE2 {vid} {' '.join(_fmt(v) for v in p)}")
    for (i, j), z, info in zip(graph.edge_ij.tolist(), graph.edge_z, graph.edge_info, strict=True):
        upper = [info[0, 0], info[0, 1], info[0, 2], info[1, 1], info[1, 2], info[2, 2]]
        nums = " ".join(_fmt(v) for v in (*z, *upper))
        lines.append(f"EDGE_SE2 {i} {j} {nums}")
    for vid in graph.fixed:
        lines.append(f"FIX {vid}")
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def chained_odometry(graph: G2oGraph, *, first_pose: FloatArray | None = None) -> FloatArray:
    """Initial guess (N, 3) for ``graph.node_ids`` by chaining the edges ``i -> i+1``.

    Raises :class:`G2oError` if an odometry edge ``k -> k+1`` (either direction) is missing.
    """
    ids = graph.node_ids
    odo: dict[int, FloatArray] = {}
    for (i, j), z in zip(graph.edge_ij.tolist(), graph.edge_z, strict=True):
        if j == i + 1 and i not in odo:
            odo[i] = z
        elif i == j + 1 and j not in odo:
            odo[j] = se2.inverse(z)
    poses = np.zeros((ids.size, 3))
    if ids.size == 0:
        return poses
    poses[0] = np.zeros(3) if first_pose is None else first_pose
    for n in range(1, ids.size):
        prev = int(ids[n - 1])
        if int(ids[n]) != prev + 1 or prev not in odo:
            raise G2oError(
                f"chained odometry: no edge between vertices {prev} and {prev + 1} "
                "(initial_poses(graph, 'chained') falls back to the spanning tree)"
            )
        poses[n] = se2.compose(poses[n - 1], odo[prev])
    return poses


StartKind = Literal["file", "chained", "tree"]


@dataclass(frozen=True)
class G2oStart:
    """An initial estimate: ``poses`` (N, 3) in ``graph.node_ids`` order, the ``kind`` that made
    it, and ``note``: empty, or why the requested kind fell back to the spanning tree."""

    poses: FloatArray
    kind: StartKind
    note: str = ""


def component_roots(graph: G2oGraph) -> IntArray:
    """The smallest vertex id of every connected component of ``graph`` (sorted); a vertex
    without edges is a component of its own."""
    ids = graph.node_ids
    if ids.size == 0:
        return ids
    labels = component_labels(ids.size, np.searchsorted(ids, graph.edge_ij))
    first = np.full(int(labels.max()) + 1, ids.size, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(ids.size))
    return ids[np.sort(first)]


def _file_poses(graph: G2oGraph) -> tuple[FloatArray, IntArray]:
    """The file's vertex poses in ``node_ids`` order (identity where absent) and the ids of
    the nodes without a ``VERTEX_SE2``."""
    ids = graph.node_ids
    poses = np.zeros((ids.size, 3))
    poses[np.searchsorted(ids, graph.vertex_ids)] = graph.vertex_poses
    return poses, np.setdiff1d(ids, graph.vertex_ids)


def _spanning_tree(graph: G2oGraph, current: FloatArray) -> FloatArray:
    ids = graph.node_ids
    roots = np.searchsorted(ids, component_roots(graph))
    factors = Pose2Factors(
        n=int(ids.size),
        ij=np.searchsorted(ids, graph.edge_ij),
        z=graph.edge_z,
        info=graph.edge_info,
        prior_index=roots,
        prior_pose=current[roots],
        prior_info=np.tile(np.eye(3) * 1e12, (roots.size, 1, 1)),
    )
    return spanning_tree_from_factors(factors, current)


def initial_poses(graph: G2oGraph, kind: StartKind = "chained") -> G2oStart:
    """Initial estimate (N, 3) of ``graph.node_ids`` (see module docstring).

    ``"file"``: the ``VERTEX_SE2`` poses; ``"chained"``: :func:`chained_odometry` from the first
    vertex's file pose (identity if absent); ``"tree"``: the spanning tree over all edges, every
    component rooted at its smallest id at that vertex's file pose (identity if absent), edges
    weighted by their covariance. ``"file"`` with vertices missing from the file and
    ``"chained"`` on a chain with a gap fall back to ``"tree"``; the result's ``note`` says why.
    """
    if kind not in ("file", "chained", "tree"):
        raise ValueError(f"initial_poses: unknown kind {kind!r}; expected file, chained or tree")
    file_poses, missing = _file_poses(graph)
    if graph.node_ids.size == 0:
        return G2oStart(file_poses, kind)
    note = ""
    if kind == "file":
        if missing.size == 0:
            return G2oStart(file_poses, "file")
        note = (
            f"{missing.size} of {graph.node_ids.size} vertices have no VERTEX_SE2 "
            f"(first: {int(missing[0])}); initialized by spanning tree over all edges"
        )
    elif kind == "chained":
        try:
            return G2oStart(chained_odometry(graph, first_pose=file_poses[0]), "chained")
        except G2oError as err:
            reason = str(err).removeprefix("chained odometry: ").split(" (")[0]
            note = f"odometry chain broken ({reason}); initialized by spanning tree over all edges"
    return G2oStart(_spanning_tree(graph, file_poses), "tree", note)


def to_gtsam(
    graph: G2oGraph, *, prior_sigma: float | None = 1e-6, poses: FloatArray | None = None
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """``BetweenFactorPose2`` per edge (keys = vertex ids) and the vertices' values.

    ``prior_sigma`` adds a tight prior at its value on the first vertex of every connected
    component (:func:`component_roots`; the gauge freedom of each), or none when ``None``.
    ``poses`` (N, 3), in ``graph.node_ids`` order, replaces the vertex values; without it every
    node needs a ``VERTEX_SE2`` (raises :class:`G2oError` naming a missing one).
    """
    fg = gtsam.NonlinearFactorGraph()
    for (i, j), z, info in zip(graph.edge_ij.tolist(), graph.edge_z, graph.edge_info, strict=True):
        noise = gtsam.noiseModel.Gaussian.Information(info)
        fg.add(gtsam.BetweenFactorPose2(i, j, se2.pose2(z), noise))
    values = gtsam.Values()
    if poses is None:
        missing = np.setdiff1d(graph.node_ids, graph.vertex_ids)
        if missing.size:
            raise G2oError(
                f"to_gtsam: vertex {int(missing[0])} (and {missing.size - 1} more) has edges but "
                "no VERTEX_SE2; pass poses=initial_poses(graph, ...).poses"
            )
        for vid, p in zip(graph.vertex_ids.tolist(), graph.vertex_poses, strict=True):
            values.insert(vid, se2.pose2(p))
    else:
        ids = graph.node_ids
        if poses.shape != (ids.size, 3):
            raise ValueError(f"poses has shape {poses.shape}, expected {(ids.size, 3)}")
        for vid, p in zip(ids.tolist(), poses, strict=True):
            values.insert(vid, se2.pose2(p))
    if prior_sigma is not None:
        noise = gtsam.noiseModel.Isotropic.Sigma(3, prior_sigma)
        for root in component_roots(graph).tolist():
            fg.add(gtsam.PriorFactorPose2(root, values.atPose2(root), noise))
    return fg, values

"""Corpus of terrain grids recorded from simulator runs, and training of the codec models
(issue 5; paper 4.3.4: "we use a large corpus of terrain maps and empirically measure the
conditional probability of a pixel in terms of its neighbors").

:func:`record_corpus` runs whole robot teams in simulated worlds (lockstep, no radio): every
robot's own node (:class:`robot.node.RobotNode`) drives seeded scripted goals, and every pose
node with its vertical-surface grid is kept with the robot's *real* odometry
(``pose_in_odom``, ``odom_delta``), exactly what the radio would carry. The grid is kept
uncropped (the node sends the bounding box of its occupied cells; :func:`node_crop` redoes
that crop), so that the codecs can be measured on both.

:func:`train_models` turns a corpus into the tables of :mod:`compression.models` and writes
the versioned model file the package ships. Train and test corpora come from different worlds
(world seeds), see :data:`TRAIN_RUNS` / :data:`TEST_RUNS`.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from compression.model_file import ModelFile
from compression.registry import GridReference, origin_cells_of

__all__ = [
    "CORPUS_DIR",
    "MODEL_SPECS",
    "TEST_RUNS",
    "TRAIN_RUNS",
    "CodingCase",
    "Corpus",
    "ModelSpec",
    "RecordRun",
    "coding_cases",
    "load_corpus",
    "node_crop",
    "record_corpus",
    "save_corpus",
    "train_models",
]

#: The corpora shipped with the package (``terrain_train.npz``, ``terrain_test.npz``).
CORPUS_DIR = Path(__file__).resolve().parents[1] / "compression" / "corpus"


class RecordRun(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """One simulator run of the corpus: a world file (under ``configs/``), its world seed,
    mission seconds, and how many scripted goals each robot gets."""

    world: str = "world/small.yaml"
    seed: int = 1
    duration_s: float = 120.0
    goals_per_robot: int = 12


#: Training worlds: the small phase with three world seeds and a full MAGIC phase.
TRAIN_RUNS: tuple[RecordRun, ...] = (
    RecordRun(world="world/small.yaml", seed=1, duration_s=240.0),
    RecordRun(world="world/small.yaml", seed=2, duration_s=240.0),
    RecordRun(world="world/small.yaml", seed=3, duration_s=240.0),
    RecordRun(world="world/magic_phase.yaml", seed=2010, duration_s=150.0),
)
#: Held-out worlds (different seeds: different buildings, fences, cars, trees, starts).
TEST_RUNS: tuple[RecordRun, ...] = (
    RecordRun(world="world/small.yaml", seed=11, duration_s=150.0),
    RecordRun(world="world/magic_phase.yaml", seed=7, duration_s=80.0),
)


@dataclass(frozen=True)
class Corpus:
    """Pose nodes with their full vertical-surface grids, grouped in per-robot sequences.

    Row ``i``: ``sequence[i]`` (one robot in one run; rows of a sequence are consecutive and in
    node order), ``node_index[i]``, ``pose_in_odom[i]`` and ``odom_delta[i]``
    (``previous_from_current``, as the :class:`~protocol.messages.PoseNode` says), and the grid
    ``grids[i]`` (``(rows, cols)`` bool) whose cell ``(r, c)`` covers
    ``origin_in_base + (c, r) * resolution_m`` in that node's base frame.
    """

    sequence: np.ndarray  # (N,) int32
    node_index: np.ndarray  # (N,) int32
    pose_in_odom: np.ndarray  # (N, 3) float64
    odom_delta: np.ndarray  # (N, 3) float64
    grids: np.ndarray  # (N, rows, cols) bool
    origin_in_base: tuple[float, float]
    resolution_m: float
    runs: tuple[str, ...]  # per sequence: "world/small.yaml:1:robot0"

    def __len__(self) -> int:
        return int(self.grids.shape[0])

    def sequences(self) -> list[np.ndarray]:
        """Row indices of each sequence, in node order."""
        return [np.flatnonzero(self.sequence == s) for s in np.unique(self.sequence)]


def node_crop(grid: np.ndarray) -> tuple[np.ndarray, int, int]:
    """The robot node's crop: the bounding box of the occupied cells, and its ``(row, col)``
    offset in ``grid`` (an empty grid crops to ``0 x 0`` at ``(0, 0)``)."""
    rows = np.flatnonzero(grid.any(axis=1))
    if len(rows) == 0:
        return np.zeros((0, 0), dtype=bool), 0, 0
    cols = np.flatnonzero(grid.any(axis=0))
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    return grid[r0:r1, c0:c1], r0, c0


def record_corpus(
    runs: Sequence[RecordRun], *, progress: Callable[[str], None] = lambda _msg: None
) -> Corpus:
    """Run each world with its whole team and keep every pose node's grid (see module doc)."""
    from compression import decode_grid, read_header
    from mission.config import CONFIGS_DIR
    from mission.run import RunConfig, scripted_goals
    from protocol.messages import GoToTask, PoseNode, TerrainGrid
    from protocol.se2 import inverse, transform_points
    from robot.node import RobotNode, RobotNodeConfig
    from sim.simulator import Simulator, load_world_config

    # any lossless codec: the grids are decoded here; the first node's grid as large as the
    # others (the corpus is of one window size, the one the codecs code in a mission)
    vs = RobotNodeConfig().vertical_surfaces
    size = vs.size_cells
    node_cfg = RobotNodeConfig(codec="zlib", first_grid_cells=size)
    half = size * vs.resolution_m / 2
    base = origin_cells_of((-half, -half), vs.resolution_m)
    seq_rows: list[int] = []
    idx_rows: list[int] = []
    poses: list[tuple[float, float, float]] = []
    deltas: list[tuple[float, float, float]] = []
    grids: list[np.ndarray] = []
    names: list[str] = []
    for run in runs:
        path = Path(run.world)
        world_cfg = load_world_config(path if path.is_absolute() else CONFIGS_DIR / path)
        world_cfg = msgspec.structs.replace(world_cfg, seed=run.seed)
        progress(f"recording {run.world} seed {run.seed} for {run.duration_s:.0f} s")
        with Simulator(world_cfg) as sim:
            goal_cfg = RunConfig(goals_per_robot=run.goals_per_robot, seed=run.seed)
            rng = np.random.default_rng(run.seed)
            chosen: list[np.ndarray] = []
            inbox: dict[int, list[object]] = {}
            nodes: dict[int, RobotNode] = {}
            goals: dict[int, np.ndarray] = {}
            for k, rid in enumerate(sim.robot_ids):
                world_goals = scripted_goals(sim, k, goal_cfg, rng, avoid=chosen)
                chosen.append(world_goals)
                goals[rid] = transform_points(inverse(sim.robot_poses()[k]), world_goals)
                inbox[rid] = []
                nodes[rid] = RobotNode(rid, send=inbox[rid].append, config=node_cfg)
            drivers = {rid: sim.driver(rid) for rid in sim.robot_ids}
            next_goal = dict.fromkeys(sim.robot_ids, 0)
            task_id = 1
            for _ in range(int(round(run.duration_s / sim.config.step_s))):
                sim.step()
                for rid in sim.robot_ids:
                    for command in nodes[rid].process(drivers[rid].poll(0.0)):
                        drivers[rid].send(command)
                    idle = nodes[rid].tasks.intent.mode.name == "IDLE"
                    if idle and next_goal[rid] < len(goals[rid]):
                        g = goals[rid][next_goal[rid]]
                        next_goal[rid] += 1
                        task = GoToTask(task_id, sim.time_s, [(float(g[0]), float(g[1]))])
                        nodes[rid].handle_downlink(task)
                        task_id += 1
            for rid in sim.robot_ids:
                seq = len(names)
                names.append(f"{run.world}:{run.seed}:robot{rid}")
                pose_nodes = {m.node_index: m for m in inbox[rid] if isinstance(m, PoseNode)}
                for msg in inbox[rid]:
                    if not isinstance(msg, TerrainGrid):
                        continue
                    node = pose_nodes[msg.node_index]
                    full = np.zeros((size, size), dtype=bool)
                    header = read_header(msg.data)
                    if header.width and header.height:
                        c0 = header.origin_cells[0] - base[0]
                        r0 = header.origin_cells[1] - base[1]
                        crop = decode_grid(msg.data)
                        full[r0 : r0 + header.height, c0 : c0 + header.width] = crop
                    seq_rows.append(seq)
                    idx_rows.append(msg.node_index)
                    poses.append(node.pose_in_odom)
                    deltas.append(node.odom_delta)
                    grids.append(full)
        progress(f"  {len(grids)} grids so far")
    return Corpus(
        sequence=np.asarray(seq_rows, dtype=np.int32),
        node_index=np.asarray(idx_rows, dtype=np.int32),
        pose_in_odom=np.asarray(poses, dtype=np.float64).reshape(-1, 3),
        odom_delta=np.asarray(deltas, dtype=np.float64).reshape(-1, 3),
        grids=np.asarray(grids, dtype=bool).reshape(-1, size, size),
        origin_in_base=(-half, -half),
        resolution_m=vs.resolution_m,
        runs=tuple(names),
    )


def save_corpus(corpus: Corpus, path: str | Path) -> None:
    """Write a corpus as a compressed ``.npz`` (grids as packed bits)."""
    n, rows, cols = corpus.grids.shape
    np.savez_compressed(
        path,
        sequence=corpus.sequence,
        node_index=corpus.node_index,
        pose_in_odom=corpus.pose_in_odom,
        odom_delta=corpus.odom_delta,
        packed=np.packbits(corpus.grids.reshape(n, rows * cols), axis=1),
        shape=np.array([n, rows, cols], dtype=np.int64),
        origin_in_base=np.array(corpus.origin_in_base, dtype=np.float64),
        resolution_m=np.array(corpus.resolution_m, dtype=np.float64),
        runs=np.array(corpus.runs, dtype=str),
    )


def load_corpus(path: str | Path) -> Corpus:
    """Read a corpus written by :func:`save_corpus`; a bad file raises ValueError naming it."""
    try:
        with np.load(path, allow_pickle=False) as f:
            n, rows, cols = (int(v) for v in f["shape"])
            bits = np.unpackbits(f["packed"], axis=1, count=rows * cols)
            corpus = Corpus(
                sequence=f["sequence"].astype(np.int32),
                node_index=f["node_index"].astype(np.int32),
                pose_in_odom=f["pose_in_odom"].astype(np.float64),
                odom_delta=f["odom_delta"].astype(np.float64),
                grids=bits.reshape(n, rows, cols).astype(bool),
                origin_in_base=(float(f["origin_in_base"][0]), float(f["origin_in_base"][1])),
                resolution_m=float(f["resolution_m"]),
                runs=tuple(str(r) for r in f["runs"]),
            )
    except (OSError, KeyError, ValueError) as err:
        raise ValueError(f"{path}: not a terrain-grid corpus: {err}") from None
    for name in ("sequence", "node_index", "pose_in_odom", "odom_delta"):
        if len(getattr(corpus, name)) != n:
            raise ValueError(f"{path}: {name} has {len(getattr(corpus, name))} rows, grids {n}")
    if not (math.isfinite(corpus.resolution_m) and corpus.resolution_m > 0):
        raise ValueError(f"{path}: resolution_m must be > 0, got {corpus.resolution_m}")
    return corpus


# ---------------------------------------------------------------------------- coding cases


@dataclass(frozen=True)
class CodingCase:
    """One grid as the robot node codes it: the node's crop, its origin in cells, and the
    reference an inter-frame codec would use (the previous node's grid), if there is one."""

    grid: np.ndarray
    origin_cells: tuple[int, int]
    reference: GridReference | None
    run: str  # "world:seed" of the recording


def coding_cases(corpus: Corpus) -> list[CodingCase]:
    """The corpus's grids in sequence order, cropped as the node crops them, each with the
    previous node's grid as reference (none for a sequence's first node or after a gap)."""
    res = corpus.resolution_m
    base = origin_cells_of(corpus.origin_in_base, res)
    cases = [CodingCase(np.zeros((0, 0), bool), (0, 0), None, "")] * len(corpus)
    for rows in corpus.sequences():
        prev: tuple[int, np.ndarray, tuple[int, int]] | None = None
        for i in rows:
            crop, r0, c0 = node_crop(corpus.grids[i])
            origin = (base[0] + c0, base[1] + r0)
            node = int(corpus.node_index[i])
            ref = None
            if prev is not None and prev[0] == node - 1:
                delta = corpus.odom_delta[i]
                pose = (float(delta[0]), float(delta[1]), float(delta[2]))
                ref = GridReference(prev[0], prev[1], prev[2], pose, res)
            run = corpus.runs[int(corpus.sequence[i])].rsplit(":", 1)[0]
            cases[i] = CodingCase(crop, origin, ref, run)
            prev = (node, crop, origin)
    return cases


# ---------------------------------------------------------------------------- training


class ModelSpec(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """A trained codec: registry name and id, template, features and whether it adapts."""

    name: str
    codec_id: int
    template: str
    extrapolate: bool = False
    reference: bool = False
    runs: bool = False
    adaptive: bool = True
    description: str = ""


#: The trained codecs of the model file (see :mod:`compression.codecs`).
MODEL_SPECS: tuple[ModelSpec, ...] = (
    ModelSpec(
        name="magic4", codec_id=20, template="4", adaptive=False,
        description="the paper's coder: 4 neighbours, static trained probabilities",
    ),
    ModelSpec(name="magic6", codec_id=21, template="6", adaptive=False,
              description="6 neighbours, static (paper Fig. 9)"),
    ModelSpec(name="magic9", codec_id=22, template="9", adaptive=False,
              description="9 neighbours, static (paper Fig. 9)"),
    ModelSpec(name="magic10", codec_id=23, template="10", adaptive=False,
              description="10 neighbours, static (paper Fig. 9)"),
    ModelSpec(name="magic16", codec_id=24, template="16", adaptive=False,
              description="16 neighbours, static"),
    ModelSpec(name="ctx16t", codec_id=28, template="16",
              description="16 neighbours, trained prior that adapts"),
    ModelSpec(name="intra16", codec_id=30, template="16", extrapolate=True, runs=True,
              description="16 neighbours + line extrapolation + quiet runs, trained, adapts"),
    ModelSpec(name="inter16", codec_id=40, template="16", extrapolate=True, reference=True,
              runs=True, description="intra16 + the previous grid warped by odometry"),
)  # fmt: skip

#: Prior strengths tried for adaptive models (chosen by leave-one-run-out on the training set).
STRENGTHS = (1.0, 2.0, 4.0, 8.0, 16.0)


def _counts(
    spec: ModelSpec, cases: list[CodingCase]
) -> tuple[np.ndarray, np.ndarray, list[CodingCase]]:
    from compression.codecs import reference_code_for
    from compression.context_model import context_counts

    used = [c for c in cases if not spec.reference or c.reference is not None]
    refcodes = None
    if spec.reference:
        refcodes = [
            reference_code_for(c.grid.shape[0], c.grid.shape[1], c.origin_cells, c.reference)  # type: ignore[arg-type]
            for c in used
        ]
    n0, n1 = context_counts(
        [c.grid for c in used],
        spec.template,
        extrapolate=spec.extrapolate,
        refcodes=refcodes,
        runs=spec.runs,
    )
    return n0, n1, used


def _body_bytes(model: object, spec: ModelSpec, cases: list[CodingCase]) -> int:
    from compression.codecs import reference_code_for
    from compression.context_model import encode_context

    total = 0
    for c in cases:
        rc = None
        if spec.reference:
            h, w = c.grid.shape
            rc = reference_code_for(h, w, c.origin_cells, c.reference)  # type: ignore[arg-type]
        total += len(encode_context(c.grid, model, rc))  # type: ignore[arg-type]
    return total


def train_models(
    corpus: Corpus,
    *,
    version: int,
    specs: Sequence[ModelSpec] = MODEL_SPECS,
    strengths: Sequence[float] = STRENGTHS,
    progress: Callable[[str], None] = lambda _msg: None,
) -> ModelFile:
    """Count every model's contexts over ``corpus`` (paper 4.3.4's training) and choose each
    adaptive model's prior strength by leave-one-run-out: the strength whose priors, counted
    without a run, code that run in the fewest bytes, summed over runs."""
    from compression.context_model import ContextModel
    from compression.model_file import ModelFile, TrainedModel

    cases = coding_cases(corpus)
    runs = sorted({c.run for c in cases})
    models = []
    chosen: dict[str, float] = {}
    for spec in specs:
        n0, n1, used = _counts(spec, cases)
        strength = 1.0
        if spec.adaptive and len(runs) > 1:
            per_run = {r: _counts(spec, [c for c in used if c.run == r]) for r in runs}
            total = dict.fromkeys(strengths, 0)
            for r0, r1, held_out in per_run.values():
                for s in strengths:
                    model = ContextModel.trained(
                        spec.template,
                        n0 - r0,
                        n1 - r1,
                        strength=s,
                        adaptive=True,
                        extrapolate=spec.extrapolate,
                        reference=spec.reference,
                        runs=spec.runs,
                    )
                    total[s] += _body_bytes(model, spec, held_out)
            strength = min(strengths, key=lambda s: total[s])
            progress(
                f"{spec.name}: strength {strength:g} "
                f"({', '.join(f'{s:g}: {total[s]}' for s in strengths)} bytes held out)"
            )
        else:
            progress(f"{spec.name}: {int(n0.sum() + n1.sum())} pixels counted")
        chosen[spec.name] = strength
        models.append(
            TrainedModel(
                name=spec.name,
                codec_id=spec.codec_id,
                template=spec.template,
                extrapolate=spec.extrapolate,
                reference=spec.reference,
                adaptive=spec.adaptive,
                strength=strength,
                n0=n0,
                n1=n1,
                description=spec.description,
                runs=spec.runs,
            )
        )
    meta: dict[str, object] = {
        "trained_on": sorted(set(runs)),
        "grids": len(corpus),
        "strengths": chosen,
    }
    return ModelFile(version, tuple(models), meta)


# ---------------------------------------------------------------------------- command


def codec_command(args: argparse.Namespace) -> int:
    """``magic codec record [--split train|test] [--out NPZ]`` and ``magic codec train
    [--corpus NPZ] [--out NPZ] [--version N]`` (defaults: the shipped files). Every path is
    checked before the long work starts: a bad one is one line on stderr naming it, status 2.
    """
    import sys

    from compression.model_file import MODEL_FILE, load_model_file, save_model_file
    from protocol.process_cli import check_input_file, check_output_file, one_line

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    action = f"magic codec {args.codec_command}"
    if args.codec_command == "record":
        runs = TRAIN_RUNS if args.split == "train" else TEST_RUNS
        out = Path(args.out) if args.out else CORPUS_DIR / f"terrain_{args.split}.npz"
        if out.suffix != ".npz":  # numpy would append it: say the name that is written
            out = out.with_name(out.name + ".npz")
        try:
            check_output_file(out, "--out")
        except ValueError as err:
            say(one_line(f"{action}: {err}"))
            return 2
        corpus = record_corpus(runs, progress=say)
        save_corpus(corpus, out)
        say(f"wrote {len(corpus)} grids of {len(corpus.runs)} robot runs to {out}")
        return 0
    corpus_path = Path(args.corpus) if args.corpus else CORPUS_DIR / "terrain_train.npz"
    out = Path(args.out) if args.out else MODEL_FILE
    try:
        check_input_file(corpus_path, "--corpus")
        check_output_file(out, "--out")
        if args.version is not None and not 1 <= args.version <= 255:
            raise ValueError(f"--version: expected 1..255 (one header byte), got {args.version}")
        corpus = load_corpus(corpus_path)
        version = args.version
        if version is None:
            version = load_model_file(MODEL_FILE).version + 1 if MODEL_FILE.is_file() else 1
        model_file = train_models(corpus, version=version, progress=say)
    except ValueError as err:
        say(one_line(f"{action}: {err}"))
        return 2
    save_model_file(out, model_file)
    say(f"wrote model version {version} ({len(model_file.models)} models) to {out}")
    return 0

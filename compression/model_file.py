"""The versioned model file: trained context-model tables shipped in the package (issue 5).

Training (paper 4.3.4: "we use a large corpus of terrain maps and empirically measure the
conditional probability of a pixel in terms of its neighbors") is counting: for each model,
how often each context was followed by a 0 and by a 1 in the training corpus. The file keeps
those counts (sparse: only contexts that occurred) with each model's template, features,
strength and whether it adapts; priors are derived from them when the file is loaded, so the
numbers are exact and the file small. Its ``version`` is written in every stream coded with
its models (see :mod:`compression.registry`): a receiver with another model file refuses those
streams by name and version instead of decoding garbage.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from compression.context_model import ContextModel

__all__ = ["MODEL_FILE", "ModelFile", "TrainedModel", "load_model_file", "save_model_file"]

#: The model file this build ships and registers codecs from.
MODEL_FILE = Path(__file__).resolve().parent / "models" / "terrain_models.npz"


@dataclass(frozen=True)
class TrainedModel:
    """One trained codec's model: its registry name and id, template and features, the corpus
    counts ``n0``/``n1`` per context (dense), strength and adaptivity."""

    name: str
    codec_id: int
    template: str
    extrapolate: bool
    reference: bool
    adaptive: bool
    strength: float
    n0: np.ndarray
    n1: np.ndarray
    description: str = ""
    runs: bool = False

    def context_model(self) -> ContextModel:
        return ContextModel.trained(
            self.template,
            self.n0,
            self.n1,
            strength=self.strength,
            adaptive=self.adaptive,
            extrapolate=self.extrapolate,
            reference=self.reference,
            runs=self.runs,
        )


@dataclass(frozen=True)
class ModelFile:
    version: int
    models: tuple[TrainedModel, ...]
    meta: dict[str, object]  # what it was trained on, measured sizes


_SPEC_KEYS = (
    "name",
    "codec_id",
    "template",
    "extrapolate",
    "reference",
    "runs",
    "adaptive",
    "strength",
)


def save_model_file(path: str | Path, model_file: ModelFile) -> None:
    """Write ``model_file`` as a compressed ``.npz`` (counts sparse, specs as JSON)."""
    if not 1 <= model_file.version <= 255:
        raise ValueError(f"model version must be in 1..255, got {model_file.version}")
    arrays: dict[str, np.ndarray] = {}
    specs = []
    for m in model_file.models:
        nz = np.flatnonzero((m.n0 > 0) | (m.n1 > 0))
        arrays[f"{m.name}.index"] = nz.astype(np.uint32)
        arrays[f"{m.name}.n0"] = m.n0[nz].astype(np.uint32)
        arrays[f"{m.name}.n1"] = m.n1[nz].astype(np.uint32)
        specs.append({k: getattr(m, k) for k in _SPEC_KEYS} | {"description": m.description})
    header = {"version": model_file.version, "models": specs, "meta": model_file.meta}
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)  # type: ignore[arg-type]


def load_model_file(path: str | Path) -> ModelFile:
    """Read a model file; a malformed one raises ValueError naming the file and the problem."""
    try:
        with np.load(path, allow_pickle=False) as f:
            header = json.loads(f["header"].tobytes().decode())
            version = int(header["version"])
            models = []
            for spec in header["models"]:
                name = str(spec["name"])
                size = ContextModel.table_size(
                    spec["template"],
                    extrapolate=spec["extrapolate"],
                    reference=spec["reference"],
                    runs=spec.get("runs", False),
                )
                index = f[f"{name}.index"].astype(np.int64)
                if index.size and (index.min() < 0 or index.max() >= size):
                    raise ValueError(f"model {name!r}: context index beyond its table of {size}")
                n0 = np.zeros(size)
                n1 = np.zeros(size)
                n0[index] = f[f"{name}.n0"]
                n1[index] = f[f"{name}.n1"]
                models.append(
                    TrainedModel(
                        name=name,
                        codec_id=int(spec["codec_id"]),
                        template=str(spec["template"]),
                        extrapolate=bool(spec["extrapolate"]),
                        reference=bool(spec["reference"]),
                        adaptive=bool(spec["adaptive"]),
                        strength=float(spec["strength"]),
                        n0=n0,
                        n1=n1,
                        description=str(spec.get("description", "")),
                        runs=bool(spec.get("runs", False)),
                    )
                )
    except (OSError, KeyError, ValueError, TypeError) as err:
        raise ValueError(f"{path}: not a terrain-codec model file: {err}") from None
    if not 1 <= version <= 255:
        raise ValueError(f"{path}: model version must be in 1..255, got {version}")
    return ModelFile(version, tuple(models), dict(header.get("meta", {})))

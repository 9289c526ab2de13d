"""Predicted node trajectories of whole breasts, in millimetres, and their files.

Every model (the Att-BLSTM checkpoint and the tree baselines) predicts a breast's cached
features ``(N, T, F)`` as normalised coordinates; `breast_prediction` maps them back with the
breast's equation-1 statistics. ``predictions/<model>.npz`` in a run folder holds one
``(N, T, 3)`` float32 array per breast name, the input of the evaluation report; beside it,
``<model>.json`` records how long each breast's prediction took and on what machine.
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from numpy.typing import NDArray

from datamodules.graphs import batch_graphs
from datamodules.trajectories import Breast
from fem.contract.atomic import atomic_path
from fem.contract.trajectory import read_npz, reading_file

PRECISIONS = ("32-true", "bf16-mixed")

#: What a graph predictor takes: one breast's sample, or several as one batch.
GraphSamples = Mapping[str, NDArray] | Sequence[Mapping[str, NDArray]]


def check_precision(precision: str) -> None:
    """Refuse a precision other than `PRECISIONS`."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")


def network_predictor(
    model: torch.nn.Module, batch_size: int = 4096, precision: str = "32-true"
) -> Callable[[NDArray], NDArray[np.float32]]:
    """``(N, T, F) -> (N, T, 3)`` normalised predictions of a sequence model, in batches.

    ``precision="bf16-mixed"`` runs the matrix products in bfloat16 (autocast): 2-3x faster
    on CPUs with bfloat16 instructions (AVX512-BF16, AMX), much slower on others."""
    check_precision(precision)

    def predict(features: NDArray) -> NDArray[np.float32]:
        model.eval()
        device = next(model.parameters()).device
        out = []
        bf16 = precision == "bf16-mixed"
        with torch.no_grad(), torch.autocast(device.type, torch.bfloat16, enabled=bf16):
            for start in range(0, len(features), batch_size):
                x = torch.as_tensor(np.array(features[start : start + batch_size]), device=device)
                out.append(model(x).float().cpu().numpy())  # (B, T, 3)
        return np.concatenate(out)

    return predict


def graph_predictor(
    model: torch.nn.Module, precision: str = "32-true"
) -> Callable[[GraphSamples], NDArray[np.float32] | list[NDArray[np.float32]]]:
    """``sample -> (N, T, 3)`` normalised predictions of a graph model on one breast's sample
    (`datamodules.graphs.graph_sample` or its ``*_graph_inputs``; targets ignored), all nodes
    and steps in one pass. A list of samples (the same breast at several thicknesses, or
    several breasts with the same step count) goes through the model as one disconnected
    graph, in one pass too, and gives the list of their (N_k, T, 3) predictions.
    ``precision`` as `network_predictor`'s."""
    check_precision(precision)

    def predict(samples: GraphSamples) -> NDArray[np.float32] | list[NDArray[np.float32]]:
        if model.training:
            model.eval()
        one = isinstance(samples, Mapping)
        inputs = [
            {k: v for k, v in s.items() if k != "targets"} for s in ([samples] if one else samples)
        ]
        device = next(model.parameters()).device
        batch = {k: v.to(device) for k, v in batch_graphs(inputs).items()}
        bf16 = precision == "bf16-mixed"
        with torch.no_grad(), torch.autocast(device.type, torch.bfloat16, enabled=bf16):
            out = model(batch).float()  # (T, sum N_k, 3)
        out = out.transpose(0, 1).cpu().numpy()  # (sum N_k, T, 3)
        if one:
            return out
        return np.split(out, np.cumsum([len(s["nodes"]) for s in inputs])[:-1])

    return predict


def breast_prediction(predict: Callable[[NDArray], NDArray], breast: Breast) -> NDArray[np.float32]:
    """A breast's predicted node coordinates per step, (N, T, 3) mm."""
    return breast.normalization().invert(predict(breast.features())).astype(np.float32)


def save_predictions(
    path: str | Path,
    predict: Callable[[NDArray], NDArray],
    breasts: Iterable[Breast],
    timings: bool = True,
) -> Path:
    """Write ``{breast name: (N, T, 3) mm}`` for ``breasts`` to ``path`` (.npz, atomically) and,
    with ``timings``, the wall time of each breast's prediction (cached features to
    millimetres, s) to ``path.with_suffix(".json")``, with the machine it ran on."""
    arrays, seconds = {}, {}
    for b in breasts:
        start = time.perf_counter()
        arrays[b.name] = breast_prediction(predict, b)
        seconds[b.name] = time.perf_counter() - start
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    if not timings:
        return Path(path)
    machine = {
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "processor": platform.processor() or platform.machine(),
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }
    with atomic_path(Path(path).with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps({"seconds": seconds, "machine": machine}, indent=1))
    return Path(path)


def load_predictions(path: str | Path) -> dict[str, NDArray[np.float32]]:
    """The ``{breast name: (N, T, 3) mm}`` arrays of `save_predictions` (no pickle).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        An empty, truncated or corrupt file, or not an ``.npz`` archive of arrays
        (`fem.contract.trajectory.read_npz`); the message names the file.
    """
    return read_npz(path, "a predictions file (.npz)")


def load_prediction_seconds(path: str | Path) -> dict[str, float]:
    """``{breast name: prediction wall time, s}`` saved beside ``path``; empty if none was.

    Raises
    ------
    ValueError
        The timing file is unreadable, or its ``seconds`` are not a mapping of breast names to
        numbers; the message names the file.
    """
    timing = Path(path).with_suffix(".json")
    if not timing.exists():
        return {}
    with reading_file(timing, "a prediction timing file (.json)", b"{") as p:
        data = json.loads(p.read_text())
    seconds = data.get("seconds") if isinstance(data, dict) else None
    if not isinstance(seconds, dict) or not all(
        isinstance(s, int | float) for s in seconds.values()
    ):
        raise ValueError(f"{timing}: field 'seconds' must map breast names to seconds")
    return {name: float(s) for name, s in seconds.items()}

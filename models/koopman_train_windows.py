"""The training windows of the deep Koopman model (torch, build time only).

``SequenceSet``: every length-p window of a set of runs, normalised (states, dictionary
features, inputs) and held as one flat tensor each on the training device, with the knot
weights of the scheduled form; ``batch`` gathers a batch of windows by index. Used by
``models/koopman_train.py`` for the training batches and the validation loss.
"""
from __future__ import annotations

import functools
from typing import Sequence

import numpy as np
import torch

from models.koopman import KoopmanError, MinMaxScaling, dictionary_features, knot_weights
from models.koopman_metrics import Trajectory


class SequenceSet:
    """All length-p windows of a set of runs, gathered on the fly from one flat tensor.

    With a dictionary, its normalised features psi_n are computed once per sample here.
    """

    def __init__(
        self,
        runs: Sequence[Trajectory],
        seq_len: int,
        state_scaling: MinMaxScaling,
        input_scaling: MinMaxScaling,
        device: torch.device,
        role: str,
        dictionary: tuple[str, ...] = (),
        dictionary_scaling: MinMaxScaling | None = None,
        speed_knots: tuple[float, ...] = (),
    ) -> None:
        starts, offset = [], 0
        for run in runs:
            n_starts = len(run) - seq_len + 1
            if n_starts > 0:
                starts.append(offset + np.arange(n_starts))
            offset += len(run)
        if not starts:
            longest = max(len(r) for r in runs)
            raise KoopmanError(
                f"{role} runs are too short for sequences of length p={seq_len}: "
                f"the longest has {longest} samples"
            )
        states = np.concatenate([state_scaling.normalise(r.states) for r in runs])
        inputs = np.concatenate([input_scaling.normalise(r.inputs) for r in runs])
        psi = np.zeros((len(states), 0))
        if dictionary:
            psi = dictionary_scaling.normalise(
                dictionary_features(dictionary, np.concatenate([r.states for r in runs])))
        self.psi = torch.as_tensor(psi, dtype=torch.float32, device=device)
        weights = (knot_weights(np.array(speed_knots), np.concatenate([r.states[:, 0] for r in runs]))
                   if speed_knots else np.zeros((len(states), 0)))
        self.knot_weights = torch.as_tensor(weights, dtype=torch.float32, device=device)
        self.states = torch.as_tensor(states, dtype=torch.float32, device=device)
        self.inputs = torch.as_tensor(inputs, dtype=torch.float32, device=device)
        self.starts = torch.as_tensor(np.concatenate(starts), dtype=torch.long, device=device)
        self.offsets = torch.arange(seq_len, device=device)
        # |vx r| (m/s^2) per sample, the lateral acceleration of steady cornering; its peak over
        # each window (``peak_accel``) is worked out only when small-signal weighting asks.
        names = runs[0].state_names
        if "vx" in names and "yaw_rate" in names:
            self._lateral_accel = np.concatenate(
                [np.abs(r.states[:, names.index("vx")] * r.states[:, names.index("yaw_rate")]) for r in runs])
        else:
            self._lateral_accel = np.zeros(len(states))

    @functools.cached_property
    def peak_accel(self) -> torch.Tensor:
        """Peak |vx r| (m/s^2) over each window (n_windows,): how far into the tyres'
        nonlinear range the window goes (for ``window_weights``)."""
        rows = self.starts.cpu().numpy()[:, None] + np.arange(len(self.offsets))
        peak = self._lateral_accel[rows].max(axis=1)
        return torch.as_tensor(peak, dtype=torch.float32, device=self.states.device)

    def __len__(self) -> int:
        return int(self.starts.numel())

    def batch(self, which: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Window indices (b,) -> x_n (b, p, n_x), psi_n (b, p, n_dict), u_n (b, p - 1, n_u),
        knot weights of the first sample's speed (b, K) (K = 0 unless scheduled)."""
        rows = self.starts[which][:, None] + self.offsets
        return self.states[rows], self.psi[rows], self.inputs[rows[:, :-1]], self.knot_weights[rows[:, 0]]

    def step_knot_weights(self, which: torch.Tensor) -> torch.Tensor:
        """Window indices (b,) -> knot weights of the speed at the start of each step (b, p - 1, K)."""
        return self.knot_weights[self.starts[which][:, None] + self.offsets[:-1]]

"""The fixed dictionary psi(x) of the deep Koopman model's lifted state, numpy only.

Physics-motivated functions of the state [vx, vy, yaw_rate] (``DICTIONARY``: vy/vx, r/vx,
vx r, vx^2, the terms a single-track model is linear in), lifted between the physical state
and the learned features: z = [x; psi(x); Phi(x)] (``models/koopman.py``). The training
normalises them (``models/koopman_train.py``); the C core evaluates the same formulas
(``firmware/src/ecu_core.c``).
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from models.errors import KoopmanError

#: Speed floor (m/s) of the dictionary's 1/vx terms: below it the car barely moves laterally.
DICTIONARY_MIN_SPEED = 1.0


def _vx(state: np.ndarray) -> np.ndarray:
    return np.maximum(state[..., 0], DICTIONARY_MIN_SPEED)


#: Fixed lifting functions of the state [vx, vy, yaw_rate] as f(vx, vy, r, vx_floored),
#: on numpy arrays (...) and on Python floats alike (the single-state hot path stays scalar).
#: A single-track model's accelerations are linear in these: slip angles ~ vy/vx, r/vx;
#: the Coriolis term vx r; speed-dependent drag ~ vx^2 (scaled to keep magnitudes alike).
DICTIONARY_FORMULAS: dict[str, Any] = {
    "vy/vx": lambda vx, vy, r, vxf: vy / vxf,
    "r/vx": lambda vx, vy, r, vxf: r / vxf,
    "vx*r": lambda vx, vy, r, vxf: vx * r,
    "vx^2/100": lambda vx, vy, r, vxf: vx * vx / 100.0,
}


def _on_states(formula: Any) -> Any:
    """A formula of DICTIONARY_FORMULAS as a map of states (..., 3) -> (...)."""
    return lambda x: formula(x[..., 0], x[..., 1], x[..., 2], _vx(x))


#: The dictionary on state arrays: name -> ((..., 3) -> (...)).
DICTIONARY: dict[str, Any] = {name: _on_states(f) for name, f in DICTIONARY_FORMULAS.items()}
#: State names the dictionary's formulas assume, in order.
DICTIONARY_STATES = ("vx", "vy", "yaw_rate")


def dictionary_features(names: Sequence[str], states: np.ndarray) -> np.ndarray:
    """psi(x): states (..., n_x) starting with DICTIONARY_STATES -> (..., len(names))."""
    states = np.asarray(states, dtype=float)
    out = np.empty(states.shape[:-1] + (len(names),))
    for i, name in enumerate(names):
        out[..., i] = DICTIONARY[name](states)
    return out


def check_dictionary(names: Sequence[str], state_names: Sequence[str]) -> tuple[str, ...]:
    """The dictionary's names validated against DICTIONARY and the state names."""
    names = tuple(names)
    unknown = [n for n in names if n not in DICTIONARY]
    if unknown:
        raise KoopmanError(f"unknown dictionary functions {unknown}; known: {sorted(DICTIONARY)}")
    if names and tuple(state_names)[:3] != DICTIONARY_STATES:
        raise KoopmanError(f"the dictionary needs the states {DICTIONARY_STATES} first, got {tuple(state_names)}")
    return names

"""The life cycle of the extended state observer (eq. 13) inside a steering MPC.

Shared by every MPC that adds the observer's disturbance estimate to its prediction:
ESO-DKMPC (observer on the lifted Koopman state) and the ablation LMPC-ESO (observer on
LMPC's bicycle state [vy, yaw_rate]). The estimate used when planning step k is
w_hat[k+1] = w_hat[k] - beta2 (x_k - x_hat_k), which already contains the measurement x_k
(``models.eso.innovated_disturbance``); after the command u_k is known the observer
advances with (x_k, u_k). The observer restarts at x_k (zero estimate, flagged
``observer_reset``) on the first step, after ``reset()``, after a measurement or input it
refused, and after any step that did not see a valid sample (status NOT_RUN): then its last
(x, u) no longer describes the transition into the next sample. After a solver fallback
it advances with the fallback command, which is what the vehicle received.

Before any of this, the measured yaw rate is corrected by the estimate of its sensor bias
(``models.yaw_rate_bias``: the rate against the heading's change, the observer's output
disturbance), so the lifted observer, the prediction and the pose rows all see the
corrected rate. The estimate restarts at zero on ``reset()`` only (it is a property of the
sensor, not of the manoeuvre); a gap in the samples only skips its update.

"x" here is the observer's state, whatever the subclass's model calls its state.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from controller.base import Command, SolverStatus, StepDebug, VehicleSample
from controller.mpc_base import Plan, SteeringMpc
from controller.tuning import EsoQpMpcTuning
from models.eso import ExtendedStateObserver, PersistentInnovationBound, innovated_disturbance
from models.yaw_rate_bias import YawRateBiasState, yaw_rate_bias_update


class ObservedMpc(SteeringMpc):
    """Mixin base (put it first among the bases) holding the observer's restarts.

    A subclass sets ``self.observer`` (an ``ExtendedStateObserver``) in its constructor,
    points ``self.observer.params`` at the model of the step's speed before calling
    ``disturbance``, and calls ``observe`` from ``_after_command``.
    """

    observer: ExtendedStateObserver
    _eso_tuning: EsoQpMpcTuning
    #: Built by the first ``innovation_bound`` call (the subclass's constructor).
    _innovation_bound: PersistentInnovationBound | None = None

    def innovation_bound(self, lateral_rows: tuple[int, int]) -> PersistentInnovationBound:
        """The observer's g2 (eq. 13): the tuning's bound on the innovation's vy and yaw-rate
        entries, at ``lateral_rows`` of the observer's state. One object per controller,
        shared by the observer's parameters at every speed: its widening is the observer's
        state (``models.eso.PersistentInnovationBound``)."""
        if self._innovation_bound is None:
            tuning = self._eso_tuning
            self._innovation_bound = PersistentInnovationBound(
                lateral_rows, tuning.eso_innovation_limit, tuning.eso_innovation_persistence,
                tuning.eso_widening_lateral_accel)
        return self._innovation_bound

    def reset(self) -> None:
        """Forget plans, progress, the observer state and the yaw-rate bias estimate."""
        self._observer_running = False
        self._yaw_rate_bias = YawRateBiasState()
        super().reset()

    @property
    def yaw_rate_bias(self) -> float:
        """The yaw-rate sensor bias estimate (rad/s) the last step corrected by."""
        return self._yaw_rate_bias.bias

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        """The MPC's step on the sample with its yaw rate corrected by the bias estimate."""
        self._yaw_rate_bias = yaw_rate_bias_update(self._yaw_rate_bias, sample.yaw, sample.yaw_rate,
                                                   self._eso_tuning.yaw_rate_bias_pole, self.ts)
        if self._yaw_rate_bias.bias != 0.0:
            sample = replace(sample, yaw_rate=sample.yaw_rate - self._yaw_rate_bias.bias)
        return super().step(sample)

    def disturbance(self, observed_state: np.ndarray) -> np.ndarray:
        """w_hat (n,) including the measurement ``observed_state`` (n,); restarts the
        observer when needed (the estimate is then zero)."""
        if not self._observer_running:
            self.observer.reset(observed_state)
            self._innovation_bound_restart()
            self._observer_running = True
            self._observer_reset = True
            return self.observer.disturbance_estimate
        return innovated_disturbance(self.observer.state, observed_state, self.observer.params)

    def observe(self, observed_state: np.ndarray, model_input: np.ndarray, lateral_accel: float) -> None:
        """Advance the observer with the step's state (n,) and the input applied (n_u,); a
        non-finite value makes it restart on the next step instead. The innovation bound
        then counts the step's innovation (after the update that used it), when it widens,
        at the step's measured lateral acceleration ``lateral_accel`` (m/s^2, vx r)."""
        bound = self._innovation_bound
        # the innovation before the update moves the estimate; only a widening bound needs it
        innovation = (np.asarray(observed_state, dtype=float) - self.observer.lifted_state_estimate
                      if bound is not None and bound.widens else None)
        if not self.observer.update(observed_state, model_input):
            self._observer_running = False
            return
        if bound is not None and innovation is not None:
            bound.advance(innovation, lateral_accel)

    def _innovation_bound_restart(self) -> None:
        if self._innovation_bound is not None:
            self._innovation_bound.restart()

    def _fallback(self, status: SolverStatus, torque: float | None, plan: Plan | None = None,
                  sample: VehicleSample | None = None) -> tuple[Command, StepDebug]:
        if sample is None:  # no valid measurement this step: restart on the next good one
            self._observer_running = False
        return super()._fallback(status, torque, plan, sample)

/*
 * ESO-DKMPC's observers: the extended state observer of eq. 13 (models/eso.py,
 * controller/observed_mpc.py) and the yaw-rate sensor bias estimate
 * (models/yaw_rate_bias.py). Functions of (state, inputs, tuning) that update the state.
 */
#ifndef ECU_OBSERVER_H
#define ECU_OBSERVER_H

#include "ecu_koopman.h"

typedef struct {
  /* ESO: z_hat, w_hat (n_z,); running 0: (re)starts on the next disturbance(); reset: a
   * restart happened in this step (StepDebug.observer_reset). */
  int running, reset;
  double z_hat[ECU_NZ], w_hat[ECU_NZ];
  /* The yaw-rate bias estimate, the previous sample's heading and measured rate;
   * has_bias_previous 0: none (start, or after a gap). */
  double yaw_rate_bias, bias_previous_yaw, bias_previous_rate;
  int has_bias_previous;
  /* The innovation bound's widening (models.eso.PersistentInnovationBound): consecutive
   * steps beyond the bound with the sign saturated_sign (0: none). */
  int saturated_steps;
  double saturated_sign;
} ecu_observer_t;

/* Controller.reset: both observers start again. */
void ecu_observer_reset(ecu_observer_t *observer);

/* models.yaw_rate_bias.yaw_rate_bias_update: the bias of the measured yaw rate from the
 * heading's change (ts s apart); a non-finite sample keeps the estimate and forgets the
 * previous one. */
void ecu_observer_bias_update(ecu_observer_t *observer, const ecu_tuning_t *tuning, double ts,
                              const ecu_sample_t *sample);

/* ObservedMpc.disturbance: w (n_z,) = w_hat[k+1] including z_k, or zero on a (re)start. */
void ecu_observer_disturbance(ecu_observer_t *observer, const ecu_tuning_t *tuning, const double z[ECU_NZ],
                              double w[ECU_NZ]);

/* eso_update (eq. 13) with the step's local model; a non-finite step restarts the observer.
 * z: the measured lifted state z_k, whose B(z_k) = B + N z_k is the bilinear model's input
 * matrix (EsoParams.bilinear; the torque's N is zero). */
void ecu_observer_update(ecu_observer_t *observer, const ecu_tuning_t *tuning, const ecu_local_model_t *model,
                         const double z[ECU_NZ], double torque, double steer);

#endif

/*
 * The grip envelope (controller/grip_envelope.py): the road's grip a_max estimated from the
 * rear axle's slip beyond the nominal bicycle's linear need, and the yaw-rate bound
 * (1 + margin) a_max / vx that the QP puts on the yaw-rate rows of eq. 21 (ecu_qp.c). The
 * same operations in the same order as the Python, so that both give the same bound to the
 * bit. A function of (state, sample, parameters) that updates the state; no heap.
 */
#ifndef ECU_GRIP_H
#define ECU_GRIP_H

#include "ecu_config.h"

typedef struct {
  /* From the tuning table and the nominal bicycle, set by ecu_grip_init. */
  double slip_excess, margin, recovery_step, peak_decay, ts;
  double mass, lf, lr, cornering_stiffness_rear; /* the rear axle (RearAxle.nominal) */
  /* The estimate: the previous sample's vy (has_previous 0: none), the recent peak of the
   * lateral acceleration |a_y| and the grip (m/s^2), whether the rear axle slid last step. */
  int has_previous, sliding;
  double previous_vy, peak, grip;
} ecu_grip_t;

/* GripEnvelope(tuning, RearAxle.nominal(), ts): the table's grip fields, the rear axle of
 * cfg's grip.axle record (mass, lf, lr, Cr), the peak's decay exp(-ts / grip_peak_time) once
 * here; then ecu_grip_reset. */
void ecu_grip_init(ecu_grip_t *grip, const ecu_tuning_t *tuning, const ecu_config_t *cfg, double ts);

/* Forget the previous sample and the estimate (no bound). */
void ecu_grip_reset(ecu_grip_t *grip);

/* GripEnvelope.update: advance the estimate with the (finite) sample and return the
 * yaw-rate bound (rad/s, > 0); INFINITY when off (grip_slip_excess 0), below 3 m/s, on
 * the first sample or with the estimate at its ceiling (no evidence of a limit). */
double ecu_grip_update(ecu_grip_t *grip, const ecu_sample_t *sample);

#endif

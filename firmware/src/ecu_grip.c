/*
 * The grip envelope's estimate (see ecu_grip.h), as controller/grip_envelope.py: the
 * equations are in that module's docstring.
 */
#include <math.h>

#include "ecu_grip.h"

#define MIN_SPEED 3.0 /* m/s: grip_envelope.MIN_SPEED_M_S (no update, no bound below) */
#define MIN_GRIP 2.0  /* m/s^2: grip_envelope.MIN_GRIP_M_S2 (the estimate's floor) */
#define MAX_GRIP 12.0 /* m/s^2: grip_envelope.MAX_GRIP_M_S2 (no evidence of a limit) */

void ecu_grip_init(ecu_grip_t *grip, const ecu_tuning_t *tuning, const ecu_config_t *cfg, double ts) {
  grip->slip_excess = tuning->grip_slip_excess;
  grip->margin = tuning->grip_margin;
  grip->recovery_step = tuning->grip_recovery * ts;
  grip->peak_decay = exp(-ts / tuning->grip_peak_time); /* the libm of Python's math.exp */
  grip->ts = ts;
  grip->mass = cfg->grip_mass;
  grip->lf = cfg->grip_lf;
  grip->lr = cfg->grip_lr;
  grip->cornering_stiffness_rear = cfg->grip_cr;
  ecu_grip_reset(grip);
}

void ecu_grip_reset(ecu_grip_t *grip) {
  grip->has_previous = 0;
  grip->previous_vy = 0.0;
  grip->peak = 0.0;
  grip->grip = MAX_GRIP;
  grip->sliding = 0;
}

/* Python's max(a, b) and min(a, b) of two finite floats: a unless b is beyond it. */
static double py_max(double a, double b) { return b > a ? b : a; }
static double py_min(double a, double b) { return b < a ? b : a; }

double ecu_grip_update(ecu_grip_t *grip, const ecu_sample_t *sample) {
  if (!(grip->slip_excess > 0.0)) return INFINITY;
  const int had_previous = grip->has_previous;
  const double previous = grip->previous_vy;
  grip->previous_vy = sample->vy;
  grip->has_previous = 1;
  if (!had_previous || sample->vx < MIN_SPEED) return INFINITY;
  const double vx = sample->vx, vy = sample->vy, yaw_rate = sample->yaw_rate;
  const double lateral_accel = (vy - previous) / grip->ts + yaw_rate * vx;
  const double rear_slip = (grip->lr * yaw_rate - vy) / vx;
  /* RearAxle.linear_slip: the rear axle carries m lf / L of the lateral force. */
  const double linear_slip =
      grip->mass * grip->lf / (grip->lf + grip->lr) * lateral_accel / grip->cornering_stiffness_rear;
  grip->peak = py_max(fabs(lateral_accel), grip->peak * grip->peak_decay);
  grip->sliding = fabs(rear_slip) - fabs(linear_slip) > grip->slip_excess;
  if (grip->sliding) grip->grip = py_max(grip->peak, MIN_GRIP);
  else grip->grip = py_min(grip->grip + grip->recovery_step, MAX_GRIP);
  if (grip->grip >= MAX_GRIP) return INFINITY; /* no evidence of a limit: no bound */
  return (1.0 + grip->margin) * grip->grip / vx;
}

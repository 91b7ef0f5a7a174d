/*
 * The node's mode logic (see ecu_modes.h); the thresholds are the contract's.
 */
#include <math.h>

#include "ecu_modes.h"

static double clamp(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

int ecu_mode_transition(int from, const ecu_events_t *e) {
  if (from == ECU_FAULT) return ECU_FAULT;
  if (e->load_failed) return ECU_FAULT;
  if (from == ECU_INIT) return e->sample_seen ? ECU_STANDBY : ECU_INIT;
  int disengage = !e->planner_ok || !e->engage || !e->path_known;
  if (from == ECU_STANDBY) return !disengage && e->rearmed && e->sample_fresh ? ECU_ACTIVE : ECU_STANDBY;
  if (from == ECU_SAFE_STOP) return disengage && e->standstill ? ECU_STANDBY : ECU_SAFE_STOP;
  if (e->sample_lost || e->controller_failed) return ECU_SAFE_STOP; /* before disengaging, as in Python */
  if (disengage) return ECU_STANDBY;
  if (!e->sample_fresh) return ECU_DEGRADED;
  return ECU_ACTIVE;
}

void ecu_safe_stop_command(double previous_valid_steer, int standstill, double *steer, double *torque) {
  double max_step = SAFE_STOP_STEER_RATE * (CONTROL_PERIOD_MS / 1000.0);
  *steer = previous_valid_steer - clamp(previous_valid_steer, -max_step, max_step);
  *torque = standstill ? 0.0 : -fabs(SAFE_STOP_BRAKE);
}

int ecu_guard_command(double *steer, double *torque, double previous_valid_steer) {
  if (isfinite(*steer) && isfinite(*torque) && *steer >= -STEER_LIMIT && *steer <= STEER_LIMIT &&
      *torque >= -TORQUE_LIMIT && *torque <= TORQUE_LIMIT)
    return 0;
  *steer = clamp(isfinite(previous_valid_steer) ? previous_valid_steer : 0.0, -STEER_LIMIT, STEER_LIMIT);
  *torque = 0.0;
  return 1;
}

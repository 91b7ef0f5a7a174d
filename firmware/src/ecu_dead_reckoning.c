/*
 * Dead reckoning (see ecu_dead_reckoning.h), operation for operation as the Python.
 */
#include <math.h>

#include "ecu_contract.h"
#include "ecu_dead_reckoning.h"

#define DEAD_RECKONING_TS 0.025

int ecu_dead_reckoning(ecu_sample_t *s, double elapsed_s) {
  if (!(isfinite(s->x) && isfinite(s->y) && isfinite(s->yaw) && isfinite(s->vx) && isfinite(s->vy) &&
        isfinite(s->yaw_rate) && isfinite(elapsed_s) && elapsed_s >= 0.0))
    return -1;
  double x = s->x, y = s->y, yaw = s->yaw;
  int n_steps = elapsed_s > 0.0 ? (int)ceil(elapsed_s / DEAD_RECKONING_TS - 1e-9) : 0;
  for (int step = 0; step < n_steps; step++) {
    double dt = fmin(DEAD_RECKONING_TS, elapsed_s - step * DEAD_RECKONING_TS);
    double nx = x + dt * (s->vx * cos(yaw) - s->vy * sin(yaw));
    double ny = y + dt * (s->vx * sin(yaw) + s->vy * cos(yaw));
    yaw = yaw + dt * s->yaw_rate;
    x = nx;
    y = ny;
  }
  if (!(yaw >= -PI && yaw < PI)) {
    double m = fmod(yaw + PI, TWO_PI);
    if (m < 0.0) m += TWO_PI;
    yaw = m - PI;
  }
  s->x = x;
  s->y = y;
  s->yaw = yaw;
  return 0;
}

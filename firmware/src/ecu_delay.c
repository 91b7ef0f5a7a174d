/*
 * Delay compensation's window: controller/delay_compensation.py operation for operation.
 */
#include <math.h>

#include "ecu_delay.h"

double ecu_total_delay(double fixed_s, double age_s) {
  if (fixed_s <= 0.0) return 0.0;
  double age = isfinite(age_s) && age_s > 0.0 ? age_s : 0.0;
  return fixed_s + age;
}

void ecu_delay_window(double delay_s, double ts, const double *history, int n, ecu_delay_window_t *window) {
  double steps = floor(delay_s / ts);
  int whole = steps < ECU_COMMAND_HISTORY - 1 ? (int)steps : ECU_COMMAND_HISTORY - 1;
  double fraction = delay_s / ts - whole;
  window->whole_steps = whole;
  window->fraction = fraction < 1.0 ? fraction : 1.0;
  for (int j = 0; j <= whole; j++) {
    int k = n - 1 - (whole - j);
    window->inputs[j] = history[k > 0 ? k : 0];
  }
}

void ecu_pose_after(const double pose0[3], const double states[][3], double ts, const ecu_delay_window_t *window,
                    double heading_advance, double pose[3]) {
  double x = pose0[0], y = pose0[1], yaw = pose0[2];
  for (int j = 0; j <= window->whole_steps; j++) {
    double dt = j < window->whole_steps ? ts : window->fraction * ts;
    double vx = states[j][0], vy = states[j][1], yaw_rate = states[j][2];
    double heading = yaw + heading_advance * dt * yaw_rate; /* as controller.delay_compensation */
    double cos_yaw = cos(heading), sin_yaw = sin(heading);
    double nx = x + dt * (vx * cos_yaw - vy * sin_yaw);
    double ny = y + dt * (vx * sin_yaw + vy * cos_yaw);
    yaw = yaw + dt * yaw_rate;
    x = nx;
    y = ny;
  }
  pose[0] = x;
  pose[1] = y;
  pose[2] = yaw;
}

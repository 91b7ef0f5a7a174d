/*
 * The heading target's side slip (see ecu_steady_slip.h), as controller/steady_slip.py.
 */
#include <math.h>

#include "ecu_pyfloat.h"
#include "ecu_steady_slip.h"

#define SLIP_MIN_SPEED 1.0       /* m/s: controller.steady_slip.SLIP_MIN_SPEED */
#define PI 3.141592653589793     /* math.pi: numpy.unwrap's discont, period / 2 */
#define TWO_PI 6.283185307179586 /* 2.0 * math.pi: numpy.unwrap's period */

double ecu_measured_slip(double vy, double vx) { return vy / fmax(vx, SLIP_MIN_SPEED); }

/* numpy.unwrap's correction of one step dd of the heading: 0 below pi, else the multiple of
 * 2 pi that brings dd into [-pi, pi] (+pi for a positive dd on the boundary). */
static double unwrap_correction(double dd) {
  double ddmod = py_mod(dd + PI, TWO_PI) - PI;
  if (ddmod == -PI && dd > 0.0) ddmod = PI;
  return fabs(dd) < PI ? 0.0 : ddmod - dd;
}

double ecu_reference_bend(const double *yaw, int n, int stride) {
  if (n < 3) return 0.0;
  /* The unwrapped heading at step i is yaw[i] + the running sum of the corrections up to i:
   * one pass for the last (the line's end), a second for the departures. */
  double correction = 0.0;
  for (int i = 1; i < n; i++) correction += unwrap_correction(yaw[i * stride] - yaw[(i - 1) * stride]);
  double first = yaw[0], last = yaw[(n - 1) * stride] + correction, worst = 0.0;
  correction = 0.0;
  for (int i = 0; i < n; i++) {
    if (i > 0) correction += unwrap_correction(yaw[i * stride] - yaw[(i - 1) * stride]);
    double heading = i > 0 ? yaw[i * stride] + correction : first;
    double line = first + (last - first) * ((double)i / (double)(n - 1));
    double departure = fabs(heading - line);
    if (departure > worst || isnan(departure)) worst = isnan(worst) ? worst : departure;
  }
  return worst;
}

double ecu_slip_target(double slip, double bend, double limit, double gate) {
  if (limit <= 0.0 || !isfinite(slip) || !isfinite(bend)) return 0.0;
  double fade = 1.0 - bend / gate;
  fade = fade < 0.0 ? 0.0 : (fade > 1.0 ? 1.0 : fade);
  double bounded = slip < -limit ? -limit : (slip > limit ? limit : slip);
  return bounded * fade;
}

/*
 * The heading target's steady side slip (see ecu_steady_slip.h), as controller/steady_slip.py.
 */
#include <math.h>
#include <string.h>

#include "ecu_pyfloat.h"
#include "ecu_steady_slip.h"

#define SYSTEM_MAX (ECU_NZ + ECU_NU) /* the largest n + m */
#define PI 3.141592653589793     /* math.pi: numpy.unwrap's discont, period / 2 */
#define TWO_PI 6.283185307179586 /* 2.0 * math.pi: numpy.unwrap's period */

/* Solve t y = rhs in place (rhs becomes y) by LU with partial pivoting (the first largest
 * pivot of each column, as LAPACK's dgetrf): 0, or -1 at a zero pivot. t is overwritten. */
static int lu_solve(int size, double t[SYSTEM_MAX][SYSTEM_MAX], double rhs[SYSTEM_MAX]) {
  for (int k = 0; k < size; k++) {
    int pivot = k;
    for (int i = k + 1; i < size; i++)
      if (fabs(t[i][k]) > fabs(t[pivot][k])) pivot = i;
    if (t[pivot][k] == 0.0) return -1;
    if (pivot != k) {
      double row[SYSTEM_MAX], value = rhs[k];
      memcpy(row, t[k], sizeof row);
      memcpy(t[k], t[pivot], sizeof row);
      memcpy(t[pivot], row, sizeof row);
      rhs[k] = rhs[pivot];
      rhs[pivot] = value;
    }
    for (int i = k + 1; i < size; i++) {
      double factor = t[i][k] / t[k][k];
      for (int j = k + 1; j < size; j++) t[i][j] -= factor * t[k][j];
      rhs[i] -= factor * rhs[k];
    }
  }
  for (int k = size - 1; k >= 0; k--) {
    double sum = rhs[k];
    for (int j = k + 1; j < size; j++) sum -= t[k][j] * rhs[j];
    rhs[k] = sum / t[k][k];
  }
  return 0;
}

int ecu_steady_slip_map(int n, int m, const double *A, const double *B, int vy_row, int yaw_rate_row, int vx_row,
                        double *L) {
  double t[SYSTEM_MAX][SYSTEM_MAX], y[SYSTEM_MAX];
  int held[2] = {yaw_rate_row, vx_row}, n_held = vx_row < 0 ? 1 : 2, size = n + m;
  if (n < 1 || n > ECU_NZ || m < 1 || m > ECU_NU || n_held != m || vy_row < 0 || vy_row >= n ||
      yaw_rate_row < 0 || yaw_rate_row >= n || vx_row >= n) {
    for (int i = 0; i < n && i < ECU_NZ; i++) L[i] = 0.0;
    return -1;
  }
  /* The transpose of [[I - A, -B], [selector rows of the held states]]: one solve with it
   * gives e_vy^T system^-1, whose first n entries map [w; 0] to the steady vy. */
  memset(t, 0, sizeof t);
  memset(y, 0, sizeof y);
  for (int i = 0; i < n; i++) {
    for (int j = 0; j < n; j++) t[j][i] = (i == j ? 1.0 : 0.0) - A[i * n + j];
    for (int j = 0; j < m; j++) t[n + j][i] = -B[i * m + j];
  }
  for (int k = 0; k < m; k++) t[held[k]][n + k] = 1.0;
  y[vy_row] = 1.0;
  int ok = lu_solve(size, t, y) == 0;
  for (int i = 0; ok && i < n; i++) ok = isfinite(y[i]);
  for (int i = 0; i < n; i++) L[i] = ok ? y[i] : 0.0;
  return ok ? 0 : -1;
}

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

/*
 * Python's float arithmetic where the ECU must match the Python ECU to the bit: // and %
 * as CPython computes them, repr(float).
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ecu_pyfloat.h"

/* float.__floordiv__ as CPython computes it (float_floor_div). */
double py_floordiv(double vx, double wx) {
  double mod = fmod(vx, wx), div = (vx - mod) / wx;
  if (mod != 0.0 && ((wx < 0) != (mod < 0))) div -= 1.0;
  if (div == 0.0) return copysign(0.0, vx / wx);
  double floordiv = floor(div);
  if (div - floordiv > 0.5) floordiv += 1.0;
  return floordiv;
}

/* float.__mod__ (the result takes the divisor's sign). */
double py_mod(double vx, double wx) {
  double mod = fmod(vx, wx);
  if (mod != 0.0) {
    if ((wx < 0) != (mod < 0)) mod += wx;
  } else {
    mod = copysign(0.0, wx);
  }
  return mod;
}

/* repr(float): the shortest form that reads back, ".0" added to an integral one. */
void py_repr(char *buf, size_t len, double v) {
  if (buf == NULL || len == 0) return;
  if (isnan(v)) {
    snprintf(buf, len, "nan");
    return;
  }
  if (isinf(v)) {
    snprintf(buf, len, v > 0 ? "inf" : "-inf");
    return;
  }
  int digits = 1;
  for (; digits < 17; digits++) { /* the fewest significant digits that read back */
    snprintf(buf, len, "%.*e", digits - 1, v);
    if (strtod(buf, NULL) == v) break;
  }
  snprintf(buf, len, "%.*e", digits - 1, v);
  const char *e = strchr(buf, 'e');
  int exponent = e ? atoi(e + 1) : 0;
  if (exponent < -4 || exponent >= 16) return; /* float_repr_style: 1e+308, 1.5e-05 */
  snprintf(buf, len, "%.*f", digits - 1 - exponent > 0 ? digits - 1 - exponent : 0, v);
  if (!strchr(buf, '.')) strncat(buf, ".0", len - strlen(buf) - 1);
}

/*
 * The heading target under a constant disturbance (controller/steady_slip.py): the steady
 * side slip the observer's estimate implies, the bend of the horizon's reference heading
 * and the bounded, faded target the MPC's heading moves by. Pure functions, no heap.
 */
#ifndef ECU_STEADY_SLIP_H
#define ECU_STEADY_SLIP_H

#include "ecu_build.h"

/* steady_slip_map: the row L (n,) with vy_steady = L . w for a disturbance w (n,) of
 * x+ = A x + B u + c + w, from the steady state with the yaw rate held at zero, vx held
 * (vx_row < 0: none; then m is 1) and the m inputs free: L = the first n entries of the
 * solution of [[I - A, -B], [the held states' selector rows]]^T y = e_vy (LU with partial
 * pivoting). A (n, n) and B (n, m) row-major, n <= ECU_NZ, m <= ECU_NU. Returns 0; -1 with
 * L zero when the steady state is not unique (a zero pivot), L would not be finite, or the
 * held states are not m or the sizes exceed the build's. */
int ecu_steady_slip_map(int n, int m, const double *A, const double *B, int vy_row, int yaw_rate_row, int vx_row,
                        double *L);

/* reference_bend: largest departure (rad) of the reference heading (n,), yaw[i * stride]
 * at step i, unwrapped as numpy.unwrap does, from the straight line between its ends; 0
 * when n < 3. */
double ecu_reference_bend(const double *yaw, int n, int stride);

/* slip_target: slip bounded by +-limit and scaled by clip(1 - bend / gate, 0, 1); 0 when
 * limit <= 0 or slip or bend is not finite. */
double ecu_slip_target(double slip, double bend, double limit, double gate);

#endif

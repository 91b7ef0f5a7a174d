/*
 * The heading target under a constant disturbance (controller/steady_slip.py): the measured
 * side slip, the bend of the horizon's reference heading and the bounded, faded target the
 * MPC's heading moves by. Pure functions, no heap.
 */
#ifndef ECU_STEADY_SLIP_H
#define ECU_STEADY_SLIP_H

#include "ecu_build.h"

/* measured_slip: the side slip (rad, small angle) vy / max(vx, 1 m/s). */
double ecu_measured_slip(double vy, double vx);

/* reference_bend: largest departure (rad) of the reference heading (n,), yaw[i * stride]
 * at step i, unwrapped as numpy.unwrap does, from the straight line between its ends; 0
 * when n < 3. */
double ecu_reference_bend(const double *yaw, int n, int stride);

/* slip_target: slip bounded by +-limit and scaled by clip(1 - bend / gate, 0, 1); 0 when
 * limit <= 0 or slip or bend is not finite. */
double ecu_slip_target(double slip, double bend, double limit, double gate);

#endif

/*
 * The Koopman model at run time (models/koopman.py): the lift of a sample and the model at
 * one speed. Pure functions of the configuration read at start-up.
 */
#ifndef ECU_KOOPMAN_H
#define ECU_KOOPMAN_H

#include "ecu_config.h"

/* KoopmanModel.at_speed: A, B, offset (and the steer's N in a bilinear build) at one speed. */
typedef struct {
  double A[ECU_NZ][ECU_NZ], B[ECU_NZ][ECU_NU], offset[ECU_NZ];
#if ECU_BILINEAR
  double N[ECU_NZ][ECU_NZ];
#endif
} ecu_local_model_t;

/* KoopmanModel.lift: z = [x; psi(x); Phi(x)] (n_z,) from the sample. */
void ecu_koopman_lift(const ecu_config_t *cfg, const ecu_sample_t *sample, double z[ECU_NZ]);

/* KoopmanModel.at_speed: the knots' matrices interpolated at the speed rounded to the
 * quantum (the steer's N too, KoopmanModel.bilinear_for: the same weights). */
void ecu_koopman_at_speed(const ecu_config_t *cfg, double speed, ecu_local_model_t *model);

/* sum of a[i] * b[i], i = 0..n-1, in order. */
double ecu_dot(const double *a, const double *b, int n);

#endif

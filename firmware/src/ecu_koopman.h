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
  /* A transposed (At[b][a] = A[a][b]): the prediction's sums over b for all a at once. */
  double At[ECU_NZ][ECU_NZ];
  /* The speed quantum these matrices are of (ecu_koopman_at_speed recomputes them only when
   * it changes); valid = 0 (at load) forces the next computation. */
  double key;
  int valid;
} ecu_local_model_t;

/* KoopmanModel.lift: z = [x; psi(x); Phi(x)] (n_z,) from the sample. */
void ecu_koopman_lift(const ecu_config_t *cfg, const ecu_sample_t *sample, double z[ECU_NZ]);

/* KoopmanModel.at_speed: the knots' matrices interpolated at the speed rounded to the
 * quantum (the steer's N too, KoopmanModel.bilinear_for: the same weights). They depend on
 * the quantum only, so model keeps them from the last call while the quantum stays. */
void ecu_koopman_at_speed(const ecu_config_t *cfg, double speed, ecu_local_model_t *model);

/* sum of a[i] * b[i], i = 0..n-1, in order. */
double ecu_dot(const double *a, const double *b, int n);

#endif

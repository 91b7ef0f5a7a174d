/*
 * The Koopman model's lift and speed schedule (see ecu_koopman.h), the arithmetic of
 * models/koopman.py operation for operation.
 */
#include <math.h>
#include <string.h>

#include "ecu_koopman.h"

#define NZ ECU_NZ
#define KOOPMAN_SPEED_QUANTUM 0.05 /* m/s: models.koopman.SPEED_QUANTUM */
#define DICTIONARY_MIN_SPEED 1.0   /* m/s: models.koopman.DICTIONARY_MIN_SPEED */
#define LIFT_BLOCK 8               /* encoder outputs computed together (lift) */

static double clamp(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

double ecu_dot(const double *a, const double *b, int n) {
  double sum = 0.0;
  for (int i = 0; i < n; i++) sum += a[i] * b[i];
  return sum;
}

void ecu_koopman_lift(const ecu_config_t *cfg, const ecu_sample_t *sample, double z[NZ]) {
  const double *fields = &sample->vx;
  double h_in[ECU_HIDDEN_MAX > ECU_NX ? ECU_HIDDEN_MAX : ECU_NX], h_out[ECU_HIDDEN_MAX];
  for (int i = 0; i < ECU_NX; i++) z[i] = h_in[i] = fields[cfg->state_fields[i]];
  int n_known = ECU_NX + ECU_NDICT;
  double vx = z[0], vy = z[1], r = z[2], vx_floor = fmax(vx, DICTIONARY_MIN_SPEED);
  for (int i = 0; i < ECU_NDICT; i++) {
    switch (cfg->dictionary[i]) {
      case 0: z[ECU_NX + i] = vy / vx_floor; break;
      case 1: z[ECU_NX + i] = r / vx_floor; break;
      case 2: z[ECU_NX + i] = vx * r; break;
      default: z[ECU_NX + i] = vx * vx / 100.0; break;
    }
  }
  (void)vy; /* read only by a dictionary (none in some builds) */
  (void)r;
  for (int layer = 0; layer < ECU_N_LAYERS; layer++) {
    const double *w = cfg->weights + cfg->weight_at[layer], *b = cfg->biases + cfg->bias_at[layer];
    int n_in = cfg->layer_in[layer], n_out = cfg->layer_out[layer], o = 0;
    /* LIFT_BLOCK outputs at a time: each output's sum still runs over i in order (the same
     * result to the bit as one output at a time), but the independent sums overlap in the
     * pipeline instead of each waiting on its own chain of additions. */
    for (; o + LIFT_BLOCK <= n_out; o += LIFT_BLOCK) {
      double sum[LIFT_BLOCK] = {0.0};
      for (int i = 0; i < n_in; i++)
        for (int j = 0; j < LIFT_BLOCK; j++) sum[j] += w[(o + j) * n_in + i] * h_in[i];
      for (int j = 0; j < LIFT_BLOCK; j++) h_out[o + j] = sum[j] + b[o + j];
    }
    for (; o < n_out; o++) {
      double sum = 0.0;
      for (int i = 0; i < n_in; i++) sum += w[o * n_in + i] * h_in[i];
      h_out[o] = sum + b[o];
    }
    if (layer + 1 < ECU_N_LAYERS)
      for (o = 0; o < n_out; o++) h_out[o] = tanh(h_out[o]);
    memcpy(h_in, h_out, (size_t)n_out * sizeof(double));
  }
  if (ECU_N_LAYERS > 0)
    for (int i = 0; i < cfg->layer_out[ECU_N_LAYERS - 1]; i++) z[n_known + i] = h_in[i];
}

void ecu_koopman_at_speed(const ecu_config_t *cfg, double speed, ecu_local_model_t *model) {
  if (ECU_NK == 1) {
    memcpy(model->A, cfg->A[0], sizeof model->A);
    memcpy(model->B, cfg->B[0], sizeof model->B);
    memcpy(model->offset, cfg->offset[0], sizeof model->offset);
#if ECU_BILINEAR
    memcpy(model->N, cfg->N[0], sizeof model->N);
#endif
    return;
  }
  const double *k = cfg->knots;
  double key = nearbyint(clamp(speed, k[0], k[ECU_NK - 1]) / KOOPMAN_SPEED_QUANTUM);
  double v = clamp(key * KOOPMAN_SPEED_QUANTUM, k[0], k[ECU_NK - 1]);
  int upper = 0;
  while (upper < ECU_NK && k[upper] <= v) upper++;
  upper = upper < 1 ? 1 : (upper > ECU_NK - 1 ? ECU_NK - 1 : upper);
  int lower = upper - 1;
  double frac = (v - k[lower]) / (k[upper] - k[lower]), keep = 1.0 - frac;
  for (int a = 0; a < NZ; a++) {
    for (int b = 0; b < NZ; b++) model->A[a][b] = keep * cfg->A[lower][a][b] + frac * cfg->A[upper][a][b];
    for (int b = 0; b < ECU_NU; b++) model->B[a][b] = keep * cfg->B[lower][a][b] + frac * cfg->B[upper][a][b];
    model->offset[a] = keep * cfg->offset[lower][a] + frac * cfg->offset[upper][a];
#if ECU_BILINEAR
    for (int b = 0; b < NZ; b++) model->N[a][b] = keep * cfg->N[lower][a][b] + frac * cfg->N[upper][a][b];
#endif
  }
}

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

static double clamp(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* One layer's affine map h_out = W h_in + b over the input-major weights (ecu_config.h),
 * BLOCK outputs at a time: each output's sum still runs over i in order from 0.0,
 * then + b (the same result to the bit as one output at a time: lanes are added and
 * multiplied as doubles, and ISO C mode contracts nothing into fused multiply-adds), while
 * the block's independent sums sit side by side in vector registers (GCC's vector
 * extension: SSE2 / NEON, or scalar code where there is none) and read neighbouring
 * weights. The weights are doubles, or floats where every weight of the layer is a float
 * exactly (ecu_data.c): converted to double they are the same numbers, in half the bytes
 * the lift streams through the cache each step. LAYER_KERNEL(name, weight type, lane width,
 * block, attributes) defines one such function. */
#define LAYER_KERNEL(NAME, WEIGHT, LANE, BLOCK, LOAD, ATTRIBUTES)                               \
  ATTRIBUTES static void NAME(const WEIGHT *w, const double *b, int n_in, int n_out,           \
                              const double *h_in, double *h_out) {                             \
    typedef double lane_t __attribute__((vector_size(LANE * sizeof(double))));                 \
    typedef WEIGHT weights_t __attribute__((vector_size(LANE * sizeof(WEIGHT))));              \
    int o = 0;                                                                                 \
    (void)sizeof(weights_t); /* LOAD_SINGLE's */                                               \
    LAYER_BLOCKS(BLOCK, LANE, LOAD)     /* the wide blocks */                                  \
    LAYER_BLOCKS(2 * LANE, LANE, LOAD)  /* what is left, two vectors at a time */              \
    LAYER_BLOCKS(LANE, LANE, LOAD)      /* one vector */                                       \
    for (; o < n_out; o++) {            /* the last outputs one by one */                      \
      double sum = 0.0;                                                                        \
      for (int i = 0; i < n_in; i++) sum += (double)w[i * n_out + o] * h_in[i];                \
      h_out[o] = sum + b[o];                                                                   \
    }                                                                                          \
  }
/* Outputs o.. in blocks of N (LANE-wide vectors of sums) while N of them are left. */
#define LAYER_BLOCKS(N, LANE, LOAD)                                                            \
  for (; o + (N) <= n_out; o += (N)) {                                                         \
    lane_t sum[(N) / (LANE)];                                                                  \
    for (int j = 0; j < (N) / (LANE); j++) sum[j] = (lane_t){0.0};                            \
    for (int i = 0; i < n_in; i++) {                                                           \
      lane_t hi;                                                                               \
      for (int k = 0; k < (LANE); k++) hi[k] = h_in[i];                                        \
      for (int j = 0; j < (N) / (LANE); j++) sum[j] += LOAD(w + i * n_out + o + j * (LANE)) * hi; \
    }                                                                                          \
    for (int j = 0; j < (N) / (LANE); j++) memcpy(h_out + o + j * (LANE), &sum[j], sizeof sum[j]); \
    for (int j = 0; j < (N); j++) h_out[o + j] += b[o + j];                                    \
  }
/* LANE weights from p as a vector of doubles: as they are, or floats converted. */
#define LOAD_DOUBLE(p) __extension__({ lane_t v_; memcpy(&v_, (p), sizeof v_); v_; })
#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
/* SSE2 (x86-64's baseline): two floats widened by one cvtps2pd from memory. */
#define LOAD_SINGLE(p) _mm_cvtps_pd(_mm_castsi128_ps(_mm_loadl_epi64((const __m128i *)(const void *)(p))))
#else
#define LOAD_SINGLE(p) __extension__({ weights_t v_; memcpy(&v_, (p), sizeof v_); __builtin_convertvector(v_, lane_t); })
#endif

LAYER_KERNEL(layer_double, double, 2, 16, LOAD_DOUBLE, )
LAYER_KERNEL(layer_single, float, 2, 16, LOAD_SINGLE, )
#if defined(__x86_64__) && defined(__GNUC__) && !defined(ECU_NO_AVX)
/* The same on AVX's 4-double registers where the CPU has them (chosen at run time: the
 * build stays x86-64 baseline). AVX alone has no fused multiply-add. */
#define LOAD_SINGLE_AVX(p) _mm256_cvtps_pd(_mm_loadu_ps(p))
LAYER_KERNEL(layer_double_avx, double, 4, 32, LOAD_DOUBLE, __attribute__((target("avx"))))
LAYER_KERNEL(layer_single_avx, float, 4, 32, LOAD_SINGLE_AVX, __attribute__((target("avx"))))
static int has_avx(void) {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx");
}
#else
#define layer_double_avx layer_double
#define layer_single_avx layer_single
static int has_avx(void) { return 0; }
#endif

double ecu_dot(const double *a, const double *b, int n) {
  double sum = 0.0;
  for (int i = 0; i < n; i++) sum += a[i] * b[i];
  return sum;
}

void ecu_koopman_lift(const ecu_config_t *cfg, const ecu_sample_t *sample, double z[NZ]) {
  const double *fields = &sample->vx;
  const int avx = has_avx();
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
    const double *w = cfg->weights.value + cfg->weight_at[layer], *b = cfg->biases + cfg->bias_at[layer];
    const int n_in = cfg->layer_in[layer], n_out = cfg->layer_out[layer];
    if (cfg->weights_single[layer])
      (avx ? layer_single_avx : layer_single)(cfg->weights.single + 2 * cfg->weight_at[layer], b, n_in, n_out, h_in,
                                              h_out);
    else
      (avx ? layer_double_avx : layer_double)(w, b, n_in, n_out, h_in, h_out);
    if (layer + 1 < ECU_N_LAYERS)
      for (int o = 0; o < n_out; o++) h_out[o] = tanh(h_out[o]);
    memcpy(h_in, h_out, (size_t)n_out * sizeof(double));
  }
  if (ECU_N_LAYERS > 0)
    for (int i = 0; i < cfg->layer_out[ECU_N_LAYERS - 1]; i++) z[n_known + i] = h_in[i];
}

static void transpose_a(ecu_local_model_t *model) {
  for (int a = 0; a < NZ; a++)
    for (int b = 0; b < NZ; b++) model->At[b][a] = model->A[a][b];
}

void ecu_koopman_at_speed(const ecu_config_t *cfg, double speed, ecu_local_model_t *model) {
  if (ECU_NK == 1) {
    if (model->valid) return; /* one model at every speed */
    memcpy(model->A, cfg->A[0], sizeof model->A);
    memcpy(model->B, cfg->B[0], sizeof model->B);
    memcpy(model->offset, cfg->offset[0], sizeof model->offset);
#if ECU_BILINEAR
    memcpy(model->N, cfg->N[0], sizeof model->N);
#endif
    transpose_a(model);
    model->key = 0.0;
    model->valid = 1;
    return;
  }
  const double *k = cfg->knots;
  double key = nearbyint(clamp(speed, k[0], k[ECU_NK - 1]) / KOOPMAN_SPEED_QUANTUM);
  if (model->valid && model->key == key) return; /* the same quantum: the same matrices */
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
  transpose_a(model);
  model->key = key;
  model->valid = 1;
}

/*
 * The control step of the steering MPCs, a port of the Python controllers:
 *   controller/mpc_base.py     step, fallback (shifted previous plan), final guard
 *   controller/qp_mpc.py       the plan: affine state prediction, pose linearisation, QP
 *   controller/lifted_mpc.py   Koopman prediction (scheduled model at the measured speed;
 *                              with the steer-bilinear term, B(z_k) held over the horizon)
 *   controller/eso_dkmpc.py    + the ESO's disturbance estimate (controller/observed_mpc.py)
 *   controller/lmpc.py         bicycle prediction (discretised at the measured speed)
 *   controller/reference.py    path progress and the pose reference over the horizon
 * Quantities keep the Python names; array shapes are in the comments. All storage is
 * static: nothing is allocated, so a step's time is bounded by its loops.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "ecu_internal.h"
#include "os.h"

#define NP ECU_NP_MAX
#define NC ECU_NC_MAX
#define NZ ECU_NZ
#define STEER_LIMIT 0.3           /* rad: controller.base.STEER_LIMIT_RAD */
#define TWO_PI 6.283185307179586  /* 2.0 * math.pi */
#define KOOPMAN_SPEED_QUANTUM 0.05 /* m/s: models.koopman.SPEED_QUANTUM */
#define LMPC_SPEED_QUANTUM 0.01    /* m/s: controller.lmpc.SPEED_QUANTUM */
#define LMPC_MIN_MODEL_SPEED 1.0   /* m/s: controller.lmpc.MIN_MODEL_SPEED */
#define DICTIONARY_MIN_SPEED 1.0   /* m/s: models.koopman.DICTIONARY_MIN_SPEED */
#define LIFT_BLOCK 8               /* encoder outputs computed together (lift) */

static ecu_config_t cfg;
static int loaded, controller;
static const ecu_tuning_t *tun;
static int n_pred, n_ctrl;

/* Path (ReferencePath arrays) and progress (PathTracker). */
static double path_x[ECU_MAX_PATH_POINTS], path_y[ECU_MAX_PATH_POINTS];
static double path_yaw[ECU_MAX_PATH_POINTS], path_s[ECU_MAX_PATH_POINTS];
static int path_n, has_progress;
static double progress;

/* SteeringMpc state: last good plan (Nc,), its age, the last command. */
static double plan_steer[NC];
static int has_plan, plan_age, has_last;
static double last_steer, last_torque;

/* ESO (ESO-DKMPC): z_hat, w_hat (n_z,); the step's local model (A, B, offset, and the
 * steer's N in a bilinear build) and z_k. */
static int observer_running, observer_reset;
static double z_hat[NZ], w_hat[NZ];
static double local_A[NZ][NZ], local_B[NZ][ECU_NU], local_offset[NZ];
#if ECU_BILINEAR
static double local_N[NZ][NZ];
#endif
static double lifted[NZ];
static double decay_power[NP]; /* disturbance_decay^i, i = 0..Np-1 (set at load: pow once) */
/* Yaw-rate sensor bias estimate (models/yaw_rate_bias.py): the estimate, the previous
 * sample's heading and measured rate; has_bias_previous 0: none (start, or after a gap). */
static double yaw_rate_bias, bias_previous_yaw, bias_previous_rate;
static int has_bias_previous;

static double clamp(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

const char *ecu_build_shapes(void) {
  static char text[256];
  static const int widths[] = ECU_LAYER_WIDTHS;
  snprintf(text, sizeof text,
           "n_x %d, n_u %d, n_z %d, dictionary %d, knots %d, form %d, encoder %d layers (last %d), "
           "Np/Nc eso-dkmpc %d/%d dkmpc %d/%d lmpc %d/%d",
           ECU_NX, ECU_NU, ECU_NZ, ECU_NDICT, ECU_NK, ECU_FORM, ECU_N_LAYERS, widths[ECU_N_LAYERS - 1],
           ECU_NP_ESO_DKMPC, ECU_NC_ESO_DKMPC, ECU_NP_DKMPC, ECU_NC_DKMPC, ECU_NP_LMPC, ECU_NC_LMPC);
  return text;
}

/* ------------------------------------------------------------------ start-up */
int ecu_load(const char *data_path, const char *name, char *err, size_t err_len) {
  static const char *const NAMES[ECU_N_CONTROLLERS] = {"eso-dkmpc", "dkmpc", "lmpc"};
  int id = -1;
  for (int i = 0; i < ECU_N_CONTROLLERS; i++)
    if (name && strcmp(name, NAMES[i]) == 0) id = i;
  if (id < 0) {
    snprintf(err, err_len, "unknown controller %s; the C core has eso-dkmpc, dkmpc, lmpc", name ? name : "(null)");
    return -1;
  }
  loaded = 0;
  if (ecu_read_data(data_path, &cfg, err, err_len) != 0) return -1;
  const ecu_tuning_t *t = &cfg.tuning[id];
  if (id == ECU_ESO_DKMPC && !(t->eso_pole >= 0.0 && t->eso_pole < 1.0 && t->eso_second_pole >= 0.0 &&
                               t->eso_second_pole < 1.0 && isfinite(t->disturbance_decay) &&
                               t->eso_innovation_limit >= 0.0 && t->eso_innovation_limit <= 10.0 &&
                               t->yaw_rate_bias_pole >= 0.0 && t->yaw_rate_bias_pole <= 1.0)) {
    snprintf(err, err_len, "%s: [eso-dkmpc] eso_pole, eso_second_pole must be in [0, 1), "
             "disturbance_decay finite, eso_innovation_limit in [0, 10] and yaw_rate_bias_pole in [0, 1]",
             data_path);
    return -1;
  }
  if (ecu_qp_init(id, t, err, err_len) != 0) return -1;
  controller = id;
  tun = t;
  n_pred = t->n_pred;
  n_ctrl = t->n_ctrl;
  for (int i = 0; i < n_pred; i++) decay_power[i] = pow(t->disturbance_decay, (double)i);
  path_n = 0;
  loaded = 1;
  ecu_reset();
  return 0;
}

int ecu_set_path(const double *x, const double *y, const double *yaw, const double *s, int n, char *err,
                 size_t err_len) {
  if (n < 2 || n > ECU_MAX_PATH_POINTS) {
    snprintf(err, err_len, "path: %d points (need 2 to %d)", n, ECU_MAX_PATH_POINTS);
    return -1;
  }
  for (int i = 0; i < n; i++) {
    if (!(isfinite(x[i]) && isfinite(y[i]) && isfinite(yaw[i]) && isfinite(s[i])) || (i > 0 && !(s[i] > s[i - 1]))) {
      snprintf(err, err_len, "path: point %d is not finite or its arc length does not increase", i);
      return -1;
    }
  }
  memcpy(path_x, x, (size_t)n * sizeof(double));
  memcpy(path_y, y, (size_t)n * sizeof(double));
  memcpy(path_yaw, yaw, (size_t)n * sizeof(double));
  memcpy(path_s, s, (size_t)n * sizeof(double));
  path_n = n;
  has_progress = 0;
  return 0;
}

int ecu_path_copy(double *x, double *y, double *yaw, double *s, int max) {
  int n = path_n < max ? path_n : max;
  memcpy(x, path_x, (size_t)n * sizeof(double));
  memcpy(y, path_y, (size_t)n * sizeof(double));
  memcpy(yaw, path_yaw, (size_t)n * sizeof(double));
  memcpy(s, path_s, (size_t)n * sizeof(double));
  return path_n;
}

void ecu_reset(void) {
  has_plan = 0;
  plan_age = 0;
  has_last = 0;
  has_progress = 0;
  observer_running = 0;
  observer_reset = 0;
  yaw_rate_bias = 0.0;
  has_bias_previous = 0;
}

/* ------------------------------------------------------------------ reference */
/* numpy.interp(v, path_s, values) inside the path (ends held), for x, y and yaw at once:
 * one search for the three (out[3]). */
static void interp_pose(double v, double out[3]) {
  const double *values[3] = {path_x, path_y, path_yaw};
  int j, exact = 1;
  if (v >= path_s[path_n - 1]) j = path_n - 1;
  else if (v <= path_s[0]) j = 0;
  else {
    j = ecu_search_sorted(path_s, path_n, v, 1) - 1;
    exact = path_s[j] == v;
  }
  for (int k = 0; k < 3; k++) {
    const double *f = values[k];
    out[k] = exact ? f[j] : (f[j + 1] - f[j]) / (path_s[j + 1] - path_s[j]) * (v - path_s[j]) + f[j];
  }
}

/* PathTracker.horizon_reference: reference (Np, 3) poses at steps 1..Np. */
static void horizon_reference(double vx, double vehicle_yaw, double reference[][3]) {
  double advance = fmax(vx, 0.0) * cfg.ts;
  for (int i = 0; i < n_pred; i++) {
    double s = progress + advance * (double)(i + 1);
    double *pose = reference[i];
    interp_pose(s, pose);
    /* Beyond either end the path goes on straight along its end tangent. */
    if (s > path_s[path_n - 1]) {
      double extra = s - path_s[path_n - 1], heading = path_yaw[path_n - 1];
      pose[0] = path_x[path_n - 1] + extra * cos(heading);
      pose[1] = path_y[path_n - 1] + extra * sin(heading);
    } else if (s < 0.0) {
      pose[0] = path_x[0] + s * cos(path_yaw[0]);
      pose[1] = path_y[0] + s * sin(path_yaw[0]);
    }
  }
  double turns = nearbyint((reference[0][2] - vehicle_yaw) / TWO_PI);
  for (int i = 0; i < n_pred; i++) reference[i][2] -= TWO_PI * turns;
}

/* ------------------------------------------------------------------ models */
/* KoopmanModel.lift: z = [x; psi(x); Phi(x)] (n_z,) from the sample. */
static void lift(const ecu_sample_t *sample, double z[NZ]) {
  const double *fields = &sample->vx;
  static double h_in[ECU_HIDDEN_MAX > ECU_NX ? ECU_HIDDEN_MAX : ECU_NX], h_out[ECU_HIDDEN_MAX];
  for (int i = 0; i < ECU_NX; i++) z[i] = h_in[i] = fields[cfg.state_fields[i]];
  int n_known = ECU_NX + ECU_NDICT;
  double vx = z[0], vy = z[1], r = z[2], vx_floor = fmax(vx, DICTIONARY_MIN_SPEED);
  for (int i = 0; i < ECU_NDICT; i++) {
    switch (cfg.dictionary[i]) {
      case 0: z[ECU_NX + i] = vy / vx_floor; break;
      case 1: z[ECU_NX + i] = r / vx_floor; break;
      case 2: z[ECU_NX + i] = vx * r; break;
      default: z[ECU_NX + i] = vx * vx / 100.0; break;
    }
  }
  (void)vy; /* read only by a dictionary (none in some builds) */
  (void)r;
  for (int layer = 0; layer < ECU_N_LAYERS; layer++) {
    const double *w = cfg.weights + cfg.weight_at[layer], *b = cfg.biases + cfg.bias_at[layer];
    int n_in = cfg.layer_in[layer], n_out = cfg.layer_out[layer], o = 0;
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
    for (int i = 0; i < cfg.layer_out[ECU_N_LAYERS - 1]; i++) z[n_known + i] = h_in[i];
}

/* KoopmanModel.at_speed: the knots' matrices interpolated at the speed rounded to the quantum
 * (the steer's N too, KoopmanModel.bilinear_for: the same weights). */
static void local_model(double speed) {
  if (ECU_NK == 1) {
    memcpy(local_A, cfg.A[0], sizeof local_A);
    memcpy(local_B, cfg.B[0], sizeof local_B);
    memcpy(local_offset, cfg.offset[0], sizeof local_offset);
#if ECU_BILINEAR
    memcpy(local_N, cfg.N[0], sizeof local_N);
#endif
    return;
  }
  const double *k = cfg.knots;
  double key = nearbyint(clamp(speed, k[0], k[ECU_NK - 1]) / KOOPMAN_SPEED_QUANTUM);
  double v = clamp(key * KOOPMAN_SPEED_QUANTUM, k[0], k[ECU_NK - 1]);
  int upper = 0;
  while (upper < ECU_NK && k[upper] <= v) upper++;
  upper = upper < 1 ? 1 : (upper > ECU_NK - 1 ? ECU_NK - 1 : upper);
  int lower = upper - 1;
  double frac = (v - k[lower]) / (k[upper] - k[lower]), keep = 1.0 - frac;
  for (int a = 0; a < NZ; a++) {
    for (int b = 0; b < NZ; b++) local_A[a][b] = keep * cfg.A[lower][a][b] + frac * cfg.A[upper][a][b];
    for (int b = 0; b < ECU_NU; b++) local_B[a][b] = keep * cfg.B[lower][a][b] + frac * cfg.B[upper][a][b];
    local_offset[a] = keep * cfg.offset[lower][a] + frac * cfg.offset[upper][a];
#if ECU_BILINEAR
    for (int b = 0; b < NZ; b++) local_N[a][b] = keep * cfg.N[lower][a][b] + frac * cfg.N[upper][a][b];
#endif
  }
}

static double dot(const double *a, const double *b, int n) {
  double sum = 0.0;
  for (int i = 0; i < n; i++) sum += a[i] * b[i];
  return sum;
}

/* models.eso.InnovationSaturation, the observer's g2: the innovation z_tilde (n_z,) scaled
 * down, direction kept, once its vy or yaw-rate entry exceeds the limit (0: no bound). */
static void bounded_innovation(const double z_tilde[NZ], double g[NZ]) {
  double limit = tun->eso_innovation_limit;
  double scale = limit == 0.0 ? 0.0 : fmax(fabs(z_tilde[1]), fabs(z_tilde[2])) / limit;
  for (int i = 0; i < NZ; i++) g[i] = scale > 1.0 ? z_tilde[i] / scale : z_tilde[i];
}

/* models.yaw_rate_bias.yaw_rate_bias_update: the bias of the measured yaw rate from the
 * heading's change; a non-finite sample keeps the estimate and forgets the previous one. */
static void update_yaw_rate_bias(const ecu_sample_t *sample) {
  double yaw = sample->yaw, rate = sample->yaw_rate;
  if (!(isfinite(yaw) && isfinite(rate))) {
    has_bias_previous = 0;
    return;
  }
  if (has_bias_previous) {
    double heading_rate = remainder(yaw - bias_previous_yaw, TWO_PI) / cfg.ts;
    double residual = 0.5 * (rate + bias_previous_rate) - heading_rate;
    double bias = yaw_rate_bias + (1.0 - tun->yaw_rate_bias_pole) * (residual - yaw_rate_bias);
    if (isfinite(bias)) yaw_rate_bias = bias;
  }
  bias_previous_yaw = yaw;
  bias_previous_rate = rate;
  has_bias_previous = 1;
}

/* ObservedMpc.disturbance: w_hat[k+1] including z_k, or zero on a (re)start. */
static void disturbance(const double z[NZ], double w[NZ]) {
  double beta2 = -(1.0 - tun->eso_pole) * (1.0 - tun->eso_second_pole), z_tilde[NZ], g[NZ];
  if (!observer_running) {
    memcpy(z_hat, z, sizeof z_hat);
    memset(w_hat, 0, sizeof w_hat);
    observer_running = 1;
    observer_reset = 1;
    memset(w, 0, NZ * sizeof(double));
    return;
  }
  for (int i = 0; i < NZ; i++) z_tilde[i] = z[i] - z_hat[i];
  memcpy(w, w_hat, NZ * sizeof(double));
  if (!isfinite(dot(z_tilde, z_tilde, NZ))) return;
  bounded_innovation(z_tilde, g);
  double next[NZ];
  for (int i = 0; i < NZ; i++) next[i] = w_hat[i] - beta2 * g[i];
  if (isfinite(dot(next, next, NZ))) memcpy(w, next, sizeof next);
}

/* eso_update (eq. 13) with the step's local model; a non-finite step restarts the observer.
 * z: the measured lifted state z_k, whose B(z_k) = B + N z_k is the bilinear model's input
 * matrix (EsoParams.bilinear; the torque's N is zero). */
static void observe(const double z[NZ], double torque, double steer) {
  double c = tun->eso_pole + tun->eso_second_pole - 1.0;
  double beta2 = -(1.0 - tun->eso_pole) * (1.0 - tun->eso_second_pole);
  double u[2] = {torque, steer}, z_tilde[NZ], g[NZ], next_z[NZ], next_w[NZ];
  for (int i = 0; i < NZ; i++) z_tilde[i] = z[i] - z_hat[i];
  bounded_innovation(z_tilde, g);
  double check = dot(z_hat, z_hat, NZ) + dot(w_hat, w_hat, NZ) + dot(u, u, 2) + 2.0 * dot(z_tilde, z_tilde, NZ);
  if (!isfinite(check)) {
    observer_running = 0;
    return;
  }
  for (int i = 0; i < NZ; i++) {
    double sum = w_hat[i] + local_offset[i];
    for (int j = 0; j < NZ; j++) {
      double beta1 = (i == j ? c : 0.0) - local_A[i][j];
      sum += local_A[i][j] * z_hat[j] - beta1 * z_tilde[j];
    }
    for (int j = 0; j < ECU_NU; j++) sum += local_B[i][j] * u[j];
#if ECU_BILINEAR
    sum += steer * dot(local_N[i], z, NZ);
#endif
    next_z[i] = sum;
    next_w[i] = w_hat[i] - beta2 * g[i];
  }
  if (!isfinite(dot(next_z, next_z, NZ) + dot(next_w, next_w, NZ))) {
    observer_running = 0;
    return;
  }
  memcpy(z_hat, next_z, sizeof z_hat);
  memcpy(w_hat, next_w, sizeof w_hat);
}

/* gain[i][:, c] of the held input map from the Markov parameters markov[k] (3,) = C A^k b:
 * column c < Nc - 1 sees the input of step c only, the last column every step from Nc - 1. */
static void held_gain(double markov[][3], double gain[][3][NC]) {
  for (int i = 0; i <= n_pred; i++) {
    for (int x = 0; x < 3; x++) {
      for (int c = 0; c < n_ctrl; c++) {
        double g = 0.0;
        if (c < n_ctrl - 1) {
          if (c < i) g = markov[i - 1 - c][x];
        } else {
          for (int j = n_ctrl - 1; j < i; j++) g += markov[i - 1 - j][x];
        }
        gain[i][x][c] = g;
      }
    }
  }
}

/* LiftedMpc.predict_states (+ EsoDkmpc.disturbance_response): free (Np + 1, 3),
 * gain (Np + 1, 3, Nc) of the states [vx, vy, yaw_rate] at steps 0..Np. */
static void predict_koopman(const ecu_sample_t *sample, double torque, double free[][3], double gain[][3][NC]) {
  double drift[NZ], w[NZ], f[NZ], next[NZ], m[NZ], markov[NP + 1][3];
  lift(sample, lifted);
  local_model(sample->vx);
  for (int i = 0; i < NZ; i++) drift[i] = local_B[i][0] * torque + local_offset[i];
  int observed = controller == ECU_ESO_DKMPC;
  if (observed) disturbance(lifted, w);
  memcpy(f, lifted, sizeof f);
  for (int x = 0; x < 3; x++) free[0][x] = f[x];
  for (int i = 0; i < n_pred; i++) {
    double decay = observed ? decay_power[i] : 0.0;
    for (int a = 0; a < NZ; a++) {
      double sum = drift[a];
      for (int b = 0; b < NZ; b++) sum += local_A[a][b] * f[b];
      next[a] = observed ? sum + decay * w[a] : sum;
    }
    memcpy(f, next, sizeof f);
    for (int x = 0; x < 3; x++) free[i + 1][x] = f[x];
  }
  /* Markov parameters C_P A^k b_steer, k = 0..Np - 1. With the bilinear term b_steer is the
   * steer column of B(z_k) = B + N z_k at the measured lifted state, held over the horizon
   * (LiftedMpc.predict_states); the drift's torque column is B's (the torque's N is zero). */
  for (int a = 0; a < NZ; a++) m[a] = local_B[a][1];
#if ECU_BILINEAR
  for (int a = 0; a < NZ; a++) m[a] += dot(local_N[a], lifted, NZ);
#endif
  for (int k = 0; k < n_pred; k++) {
    for (int x = 0; x < 3; x++) markov[k][x] = m[x];
    for (int a = 0; a < NZ; a++) {
      double sum = 0.0;
      for (int b = 0; b < NZ; b++) sum += local_A[a][b] * m[b];
      next[a] = sum;
    }
    memcpy(m, next, sizeof m);
  }
  held_gain(markov, gain);
}

/* exp(M) of a 3 x 3 matrix: scaling and squaring of a Taylor series (||M / 2^s|| <= 1/4). */
static void expm3(double m[3][3], double out[3][3]) {
  double norm = 0.0, term[3][3], tmp[3][3];
  for (int c = 0; c < 3; c++) norm = fmax(norm, fabs(m[0][c]) + fabs(m[1][c]) + fabs(m[2][c]));
  int squarings = norm > 0.25 ? (int)ceil(log2(norm / 0.25)) : 0;
  double scale = ldexp(1.0, -squarings);
  for (int a = 0; a < 3; a++)
    for (int b = 0; b < 3; b++) {
      out[a][b] = (a == b) ? 1.0 : 0.0;
      term[a][b] = out[a][b];
    }
  for (int k = 1; k <= 18; k++) {
    for (int a = 0; a < 3; a++)
      for (int b = 0; b < 3; b++)
        tmp[a][b] = (term[a][0] * m[0][b] + term[a][1] * m[1][b] + term[a][2] * m[2][b]) * scale / k;
    memcpy(term, tmp, sizeof term);
    for (int a = 0; a < 3; a++)
      for (int b = 0; b < 3; b++) out[a][b] += term[a][b];
  }
  for (int s = 0; s < squarings; s++) {
    for (int a = 0; a < 3; a++)
      for (int b = 0; b < 3; b++) tmp[a][b] = out[a][0] * out[0][b] + out[a][1] * out[1][b] + out[a][2] * out[2][b];
    memcpy(out, tmp, sizeof tmp);
  }
}

/* Lmpc.predict_states: the bicycle discretised at the measured speed (rounded), vx held. */
static void predict_bicycle(const ecu_sample_t *sample, double free[][3], double gain[][3][NC]) {
  double vx = nearbyint(fmax(sample->vx, LMPC_MIN_MODEL_SPEED) / LMPC_SPEED_QUANTUM) * LMPC_SPEED_QUANTUM;
  double cf = cfg.cf, cr = cfg.cr, m = cfg.mass, iz = cfg.yaw_inertia, lf = cfg.lf, lr = cfg.lr;
  double block[3][3] = {{-(cf + cr) / (m * vx), -(lf * cf - lr * cr) / (m * vx) - vx, cf / m},
                        {-(lf * cf - lr * cr) / (iz * vx), -(lf * lf * cf + lr * lr * cr) / (iz * vx), lf * cf / iz},
                        {0.0, 0.0, 0.0}};
  double transition[3][3], markov[NP + 1][3], state[2] = {sample->vy, sample->yaw_rate};
  double b[2], power[2][2] = {{1.0, 0.0}, {0.0, 1.0}}, next[2][2];
  for (int a = 0; a < 3; a++)
    for (int c = 0; c < 3; c++) block[a][c] *= cfg.ts;
  expm3(block, transition);
  b[0] = transition[0][2];
  b[1] = transition[1][2];
  for (int k = 0; k <= n_pred; k++) {
    free[k][0] = sample->vx;
    free[k][1] = power[0][0] * state[0] + power[0][1] * state[1];
    free[k][2] = power[1][0] * state[0] + power[1][1] * state[1];
    markov[k][0] = 0.0; /* vx does not respond to the steer */
    markov[k][1] = power[0][0] * b[0] + power[0][1] * b[1];
    markov[k][2] = power[1][0] * b[0] + power[1][1] * b[1];
    for (int a = 0; a < 2; a++)
      for (int c = 0; c < 2; c++) next[a][c] = transition[a][0] * power[0][c] + transition[a][1] * power[1][c];
    memcpy(power, next, sizeof power);
  }
  held_gain(markov, gain);
}

/* linearise_pose (controller/pose_kinematics.py): nominal poses (Np, 3) at steps 1..Np and
 * the Jacobian (Np, 3, Nc) in U, from the nominal states (Np, 3) at steps 0..Np-1. Running
 * sums in the order of numpy's cumsum. */
static void linearise_pose(const ecu_sample_t *sample, double states[][3], double gain[][3][NC], double poses[][3],
                           double jac[][3][NC]) {
  const double ts = cfg.ts;
  double yaw_sum = 0.0, x_sum = 0.0, y_sum = 0.0;
  double gain_yaw_sum[NC] = {0.0}, jx[NC] = {0.0}, jy[NC] = {0.0};
  for (int i = 0; i < n_pred; i++) {
    double yaw = yaw_sum * ts + sample->yaw; /* the yaw at step i */
    double cos_yaw = cos(yaw), sin_yaw = sin(yaw);
    double vx = states[i][0], vy = states[i][1];
    double x_rate = vx * cos_yaw - vy * sin_yaw, y_rate = vx * sin_yaw + vy * cos_yaw;
    yaw_sum += states[i][2];
    x_sum += x_rate;
    y_sum += y_rate;
    poses[i][0] = sample->x + ts * x_sum;
    poses[i][1] = sample->y + ts * y_sum;
    poses[i][2] = yaw_sum * ts + sample->yaw;
    for (int c = 0; c < n_ctrl; c++) {
      double d_yaw = gain_yaw_sum[c] * ts; /* d yaw_i / d U_c */
      /* d(x_rate) = cos dvx - sin dvy - y_rate dyaw; d(y_rate) = sin dvx + cos dvy + x_rate dyaw */
      jx[c] += cos_yaw * gain[i][0][c] - sin_yaw * gain[i][1][c] - y_rate * d_yaw;
      jy[c] += sin_yaw * gain[i][0][c] + cos_yaw * gain[i][1][c] + x_rate * d_yaw;
      gain_yaw_sum[c] += gain[i][2][c];
      jac[i][0][c] = jx[c] * ts;
      jac[i][1][c] = jy[c] * ts;
      jac[i][2][c] = gain_yaw_sum[c] * ts;
    }
  }
}

/* ------------------------------------------------------------------ the step */
typedef struct {
  int status, iterations;
  double steer[NC], cost, solve_time_s, slack_max;
} plan_t;

static double previous_steer(const ecu_sample_t *sample) {
  return has_last ? last_steer : clamp(sample->steer_angle, -STEER_LIMIT, STEER_LIMIT);
}

/* SteeringMpc.shifted_plan: the last good plan shifted to now, else the previous steer held. */
static void shifted_plan(const ecu_sample_t *sample, double nominal[NC]) {
  for (int c = 0; c < n_ctrl; c++) {
    int from = plan_age + 1 + c;
    nominal[c] = !has_plan ? previous_steer(sample) : plan_steer[from < n_ctrl ? from : n_ctrl - 1];
  }
}

/* QpSteeringMpc._plan; fills the predictions of out. */
static void make_plan(const ecu_sample_t *sample, double torque, double reference[][3], plan_t *plan,
                      ecu_output_t *out) {
  static double free[NP + 1][3], gain[NP + 1][3][NC], nominal_states[NP + 1][3];
  static double poses[NP][3], jac[NP][3][NC], pose_offset[NP][3];
  double nominal[NC], sum = 0.0;
  ecu_qp_solution_t solution;
  memset(plan, 0, sizeof *plan);
  if (controller == ECU_LMPC) predict_bicycle(sample, free, gain);
  else predict_koopman(sample, torque, free, gain);
  shifted_plan(sample, nominal);
  for (int i = 0; i <= n_pred; i++)
    for (int x = 0; x < 3; x++) {
      sum += free[i][x];
      for (int c = 0; c < n_ctrl; c++) sum += gain[i][x][c];
    }
  if (!isfinite(sum)) {
    plan->status = ECU_NUMERICAL_ERROR;
    plan->iterations = 0;
    plan->cost = NAN;
    plan->solve_time_s = 0.0;
    return;
  }
  for (int i = 0; i <= n_pred; i++)
    for (int x = 0; x < 3; x++) {
      double s = free[i][x];
      for (int c = 0; c < n_ctrl; c++) s += gain[i][x][c] * nominal[c];
      nominal_states[i][x] = s;
    }
  linearise_pose(sample, nominal_states, gain, poses, jac);
  for (int i = 0; i < n_pred; i++)
    for (int x = 0; x < 3; x++) {
      double s = 0.0;
      for (int c = 0; c < n_ctrl; c++) s += jac[i][x][c] * nominal[c];
      pose_offset[i][x] = poses[i][x] - s - reference[i][x];
    }
  /* The QP's arrays are (Np * 3, Nc) row-major: jac, and gain / free of steps 1..Np. */
  int64_t start = os_monotonic_ns();
  ecu_qp_solve(sample->vx, &jac[0][0][0], &pose_offset[0][0], previous_steer(sample), &gain[1][0][0], &free[1][0],
               nominal, &solution);
  plan->solve_time_s = 1e-9 * (double)(os_monotonic_ns() - start);
  plan->status = solution.status;
  plan->iterations = solution.iterations;
  plan->cost = solution.cost;
  plan->slack_max = fmax(fmax(solution.slack[0], solution.slack[1]), solution.slack[2]);
  for (int c = 0; c < n_ctrl; c++) plan->steer[c] = solution.steer[c];
  out->n_pred = n_pred;
  for (int i = 0; i < n_pred; i++)
    for (int x = 0; x < 3; x++) {
      double p = 0.0, s = 0.0;
      for (int c = 0; c < n_ctrl; c++) {
        p += jac[i][x][c] * (plan->steer[c] - nominal[c]);
        s += gain[i + 1][x][c] * plan->steer[c];
      }
      out->predicted_pose[i][x] = poses[i][x] + p;
      out->predicted_state[i][x] = free[i + 1][x] + s;
    }
}

/* SteeringMpc._finish: the final guard, finite and within the limits whatever came before. */
static void finish(double steer, double torque, ecu_output_t *out) {
  last_steer = isfinite(steer) ? clamp(steer, -STEER_LIMIT, STEER_LIMIT) : 0.0;
  last_torque = isfinite(torque) ? clamp(torque, cfg.torque_min, cfg.torque_max) : 0.0;
  has_last = 1;
  out->steer_angle = last_steer;
  out->drive_torque = last_torque;
}

/* SteeringMpc._after_command: the observer advances with the command the vehicle got. */
static void after_command(void) {
  if (controller == ECU_ESO_DKMPC) observe(lifted, last_torque, last_steer);
}

/* SteeringMpc._fallback (+ ObservedMpc's restart): the shifted previous plan, else the
 * previous command. torque NAN: none computed (invalid sample); sample_valid: hooks run. */
static void fallback(int status, double torque, const plan_t *plan, int sample_valid, ecu_output_t *out) {
  double steer;
  if (controller == ECU_ESO_DKMPC && !sample_valid) observer_running = 0;
  if (has_plan && plan_age + 1 < n_ctrl) {
    plan_age++;
    steer = plan_steer[plan_age];
  } else {
    has_plan = 0;
    steer = has_last ? last_steer : 0.0;
  }
  if (!sample_valid) torque = has_last ? last_torque : 0.0;
  finish(steer, torque, out);
  if (sample_valid) after_command();
  out->status = status;
  out->fallback = 1;
  out->iterations = plan ? plan->iterations : 0;
  out->solve_time_s = plan ? plan->solve_time_s : 0.0;
  out->cost = NAN;
  out->slack_max = 0.0;
  out->n_pred = 0;
  out->observer_reset = observer_reset;
  observer_reset = 0;
}

static void step_body(const ecu_sample_t *measured, ecu_output_t *out) {
  static double reference[NP][3];
  ecu_sample_t corrected = *measured;
  const ecu_sample_t *sample = &corrected;
  const double *values = &sample->vx;
  int finite = 1;
  plan_t plan;
  memset(out, 0, offsetof(ecu_output_t, predicted_pose));
  out->cost = NAN;
  for (int i = 0; i < 9; i++) finite = finite && isfinite(values[i]);
  if (!loaded) { /* no data: the safe command, never a crash */
    out->status = ECU_NOT_RUN;
    out->fallback = 1;
    return;
  }
  if (controller == ECU_ESO_DKMPC) { /* ObservedMpc.step: the yaw rate corrected by its bias */
    update_yaw_rate_bias(measured);
    if (yaw_rate_bias != 0.0) corrected.yaw_rate = measured->yaw_rate - yaw_rate_bias;
  }
  if (path_n < 2 || !finite) {
    fallback(ECU_NOT_RUN, NAN, NULL, 0, out);
    return;
  }
  double torque = clamp(cfg.speed_gain * (sample->target_speed - sample->vx), cfg.torque_min, cfg.torque_max);
  /* progress only: the control law takes the lateral error from the reference poses */
  ecu_path_track(path_x, path_y, path_s, path_n, sample->x, sample->y, &progress, &has_progress);
  horizon_reference(sample->vx, sample->yaw, reference);
  observer_reset = 0;
  make_plan(sample, torque, reference, &plan, out);
  double steer_sum = 0.0;
  for (int c = 0; c < n_ctrl; c++) steer_sum += plan.steer[c];
  if (!(plan.status == ECU_SOLVED || plan.status == ECU_SOLVED_INACCURATE) || !isfinite(steer_sum) ||
      !isfinite(plan.cost)) {
    fallback(plan.status, torque, &plan, 1, out);
    return;
  }
  for (int c = 0; c < n_ctrl; c++) plan_steer[c] = clamp(plan.steer[c], -STEER_LIMIT, STEER_LIMIT);
  has_plan = 1;
  plan_age = 0;
  finish(plan_steer[0], torque, out);
  after_command();
  out->status = plan.status;
  out->iterations = plan.iterations;
  out->solve_time_s = plan.solve_time_s;
  out->cost = plan.cost;
  out->slack_max = plan.slack_max;
  out->fallback = 0;
  out->observer_reset = observer_reset;
}

void ecu_step(const ecu_sample_t *sample, ecu_output_t *out) {
  int64_t start = os_monotonic_ns();
  step_body(sample, out);
  out->step_time_s = 1e-9 * (double)(os_monotonic_ns() - start);
}

/*
 * The horizon's prediction (see ecu_predict.h), operation for operation as the Python:
 * running sums in the order of numpy's cumsum.
 */
#include <math.h>
#include <stddef.h>
#include <string.h>

#include "ecu_predict.h"

#define NP ECU_NP_MAX
#define NC ECU_NC_MAX
#define NZ ECU_NZ
#define LMPC_SPEED_QUANTUM 0.01    /* m/s: controller.lmpc.SPEED_QUANTUM */
#define LMPC_MIN_MODEL_SPEED 1.0   /* m/s: controller.lmpc.MIN_MODEL_SPEED */
/* Rows of vx, vy and the yaw rate in the lifted state (controller.lifted_mpc.VEHICLE_STATES). */
#define ROW_VX 0
#define ROW_VY 1
#define ROW_YAW_RATE 2

/* gain[i][:, c] of the held input map from the Markov parameters markov[k] (3,) = C A^k b:
 * column c < Nc - 1 sees the input of step c only, the last column every step from Nc - 1. */
static void held_gain(int n_pred, int n_ctrl, double markov[][3], double gain[][3][NC]) {
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

void ecu_predict_koopman(const ecu_config_t *cfg, const ecu_tuning_t *tuning, ecu_observer_t *observer,
                         const double *decay_power, const ecu_sample_t *sample, double torque,
                         ecu_local_model_t *model, double lifted[NZ], double free[][3], double gain[][3][NC],
                         ecu_prediction_basis_t *basis) {
  const int n_pred = tuning->n_pred;
  double drift[NZ], w[NZ], f[NZ], next[NZ], m[NZ], markov[NP + 1][3];
  ecu_koopman_lift(cfg, sample, lifted);
  ecu_koopman_at_speed(cfg, sample->vx, model);
  for (int i = 0; i < NZ; i++) drift[i] = model->B[i][0] * torque + model->offset[i];
  int observed = observer != NULL;
  if (observed) {
    ecu_observer_disturbance(observer, tuning, lifted, w);
  }
  memcpy(basis->drift, drift, sizeof drift);
  if (observed) memcpy(basis->disturbance, w, sizeof w);
  else memset(basis->disturbance, 0, sizeof basis->disturbance);
  memcpy(f, lifted, sizeof f);
  for (int x = 0; x < 3; x++) free[0][x] = f[x];
  for (int i = 0; i < n_pred; i++) {
    double decay = observed ? decay_power[i] : 0.0;
    /* next[a] = drift[a] + sum over b in order of A[a][b] f[b], all a at once (At's rows):
     * each a's sum in the same order as one a at a time, the a side by side in vectors. */
    memcpy(next, drift, sizeof next);
    for (int b = 0; b < NZ; b++)
      for (int a = 0; a < NZ; a++) next[a] += model->At[b][a] * f[b];
    if (observed)
      for (int a = 0; a < NZ; a++) next[a] += decay * w[a];
    memcpy(f, next, sizeof f);
    for (int x = 0; x < 3; x++) free[i + 1][x] = f[x];
  }
  /* Markov parameters C_P A^k b_steer, k = 0..Np - 1. With the bilinear term b_steer is the
   * steer column of B(z_k) = B + N z_k at the measured lifted state, held over the horizon
   * (LiftedMpc.predict_states); the drift's torque column is B's (the torque's N is zero). */
  for (int a = 0; a < NZ; a++) m[a] = model->B[a][1];
#if ECU_BILINEAR
  for (int a = 0; a < NZ; a++) m[a] += ecu_dot(model->N[a], lifted, NZ);
#endif
  memcpy(basis->steer, m, sizeof m);
  for (int k = 0; k < n_pred; k++) {
    for (int x = 0; x < 3; x++) markov[k][x] = m[x];
    for (int a = 0; a < NZ; a++) next[a] = 0.0;
    for (int b = 0; b < NZ; b++)
      for (int a = 0; a < NZ; a++) next[a] += model->At[b][a] * m[b];
    memcpy(m, next, sizeof m);
  }
  held_gain(n_pred, tuning->n_ctrl, markov, gain);
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

void ecu_predict_bicycle(const ecu_config_t *cfg, const ecu_tuning_t *tuning, const ecu_sample_t *sample,
                         double free[][3], double gain[][3][NC], ecu_prediction_basis_t *basis) {
  const int n_pred = tuning->n_pred;
  double vx = nearbyint(fmax(sample->vx, LMPC_MIN_MODEL_SPEED) / LMPC_SPEED_QUANTUM) * LMPC_SPEED_QUANTUM;
  double cf = cfg->cf, cr = cfg->cr, m = cfg->mass, iz = cfg->yaw_inertia, lf = cfg->lf, lr = cfg->lr;
  double block[3][3] = {{-(cf + cr) / (m * vx), -(lf * cf - lr * cr) / (m * vx) - vx, cf / m},
                        {-(lf * cf - lr * cr) / (iz * vx), -(lf * lf * cf + lr * lr * cr) / (iz * vx), lf * cf / iz},
                        {0.0, 0.0, 0.0}};
  double transition[3][3], markov[NP + 1][3], state[2] = {sample->vy, sample->yaw_rate};
  double b[2], power[2][2] = {{1.0, 0.0}, {0.0, 1.0}}, next[2][2];
  for (int a = 0; a < 3; a++)
    for (int c = 0; c < 3; c++) block[a][c] *= cfg->ts;
  expm3(block, transition);
  b[0] = transition[0][2];
  b[1] = transition[1][2];
  for (int a = 0; a < 2; a++) {
    basis->transition[a][0] = transition[a][0];
    basis->transition[a][1] = transition[a][1];
    basis->b[a] = b[a];
    basis->lateral[a] = state[a];
  }
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
  held_gain(n_pred, tuning->n_ctrl, markov, gain);
}

void ecu_linearise_pose(double ts, const ecu_tuning_t *tuning, const ecu_sample_t *sample, double states[][3],
                        double gain[][3][NC], double poses[][3], double jac[][3][NC]) {
  const int n_pred = tuning->n_pred, n_ctrl = tuning->n_ctrl;
  double yaw_sum = 0.0, x_sum = 0.0, y_sum = 0.0;
  double gain_yaw_sum[NC] = {0.0}, jx[NC] = {0.0}, jy[NC] = {0.0};
  const double advance = tuning->pose_heading_advance * ts; /* (heading_advance * ts), as numpy */
  for (int i = 0; i < n_pred; i++) {
    double yaw = yaw_sum * ts + sample->yaw; /* the yaw at step i */
    double heading = yaw + advance * states[i][2]; /* the step's heading (pose_kinematics) */
    double cos_yaw = cos(heading), sin_yaw = sin(heading);
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
      double d_heading = d_yaw + advance * gain[i][2][c];
      /* d(x_rate) = cos dvx - sin dvy - y_rate dheading; d(y_rate) = sin dvx + cos dvy + x_rate dheading */
      jx[c] += cos_yaw * gain[i][0][c] - sin_yaw * gain[i][1][c] - y_rate * d_heading;
      jy[c] += sin_yaw * gain[i][0][c] + cos_yaw * gain[i][1][c] + x_rate * d_heading;
      gain_yaw_sum[c] += gain[i][2][c];
      jac[i][0][c] = jx[c] * ts;
      jac[i][1][c] = jy[c] * ts;
      jac[i][2][c] = gain_yaw_sum[c] * ts;
    }
  }
}

void ecu_shift_koopman(const ecu_local_model_t *model, const ecu_prediction_basis_t *basis, const double lifted[NZ],
                       const ecu_delay_window_t *window, int n_pred, double free[][3]) {
  double z[NZ], next[NZ], delta[NZ];
  memcpy(z, lifted, sizeof z);
  for (int j = 0; j <= window->whole_steps; j++) {
    const double u = window->inputs[j];
    for (int a = 0; a < NZ; a++) next[a] = 0.0;
    for (int b = 0; b < NZ; b++)
      for (int a = 0; a < NZ; a++) next[a] += model->At[b][a] * z[b];
    for (int a = 0; a < NZ; a++) next[a] = next[a] + basis->steer[a] * u + basis->drift[a] + basis->disturbance[a];
    if (j < window->whole_steps) memcpy(z, next, sizeof z);
  }
  for (int a = 0; a < NZ; a++) delta[a] = (z[a] + window->fraction * (next[a] - z[a])) - lifted[a];
  for (int i = 0; i <= n_pred; i++) {
    for (int x = 0; x < 3; x++) free[i][x] += delta[x];
    for (int a = 0; a < NZ; a++) next[a] = 0.0;
    for (int b = 0; b < NZ; b++)
      for (int a = 0; a < NZ; a++) next[a] += model->At[b][a] * delta[b];
    memcpy(delta, next, sizeof delta);
  }
}

void ecu_shift_bicycle(const ecu_prediction_basis_t *basis, const ecu_delay_window_t *window, int n_pred,
                       double free[][3]) {
  const double (*a)[2] = basis->transition;
  double x[2] = {basis->lateral[0], basis->lateral[1]}, next[2] = {0.0, 0.0}, delta[2];
  for (int j = 0; j <= window->whole_steps; j++) {
    const double u = window->inputs[j];
    next[0] = (a[0][0] * x[0] + a[0][1] * x[1]) + basis->b[0] * u;
    next[1] = (a[1][0] * x[0] + a[1][1] * x[1]) + basis->b[1] * u;
    if (j < window->whole_steps) memcpy(x, next, sizeof x);
  }
  for (int k = 0; k < 2; k++) delta[k] = (x[k] + window->fraction * (next[k] - x[k])) - basis->lateral[k];
  for (int i = 0; i <= n_pred; i++) {
    free[i][1] += delta[0];
    free[i][2] += delta[1];
    double d0 = a[0][0] * delta[0] + a[0][1] * delta[1], d1 = a[1][0] * delta[0] + a[1][1] * delta[1];
    delta[0] = d0;
    delta[1] = d1;
  }
}

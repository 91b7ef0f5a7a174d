/*
 * The observers of ESO-DKMPC (see ecu_observer.h), operation for operation as the Python.
 */
#include <math.h>
#include <string.h>

#include "ecu_observer.h"

#define NZ ECU_NZ
#define TWO_PI 6.283185307179586 /* 2.0 * math.pi */
#define PERSISTENCE_MAX_FACTOR 4.0   /* models.eso.PERSISTENCE_MAX_FACTOR */
#define SATURATED_STEPS_MAX 1000000  /* models.eso.SATURATED_STEPS_MAX */

static void restart_bound(ecu_observer_t *observer) {
  observer->saturated_steps = 0;
  observer->saturated_sign = 0.0;
}

void ecu_observer_reset(ecu_observer_t *observer) {
  observer->running = 0;
  observer->reset = 0;
  observer->yaw_rate_bias = 0.0;
  observer->has_bias_previous = 0;
  restart_bound(observer);
}

/* PersistentInnovationBound.limit: the bound of this step, widened by the steps counted. */
static double innovation_limit(const ecu_observer_t *observer, const ecu_tuning_t *tuning) {
  double limit = tuning->eso_innovation_limit, persistence = tuning->eso_innovation_persistence;
  if (persistence == 0.0 || observer->saturated_steps == 0) return limit;
  return limit * fmin(PERSISTENCE_MAX_FACTOR, 1.0 + (double)observer->saturated_steps / persistence);
}

/* models.eso.InnovationSaturation, the observer's g2: the innovation z_tilde (n_z,) scaled
 * down, direction kept, once its vy or yaw-rate entry exceeds the limit (0: no bound). */
static void bounded_innovation(const ecu_observer_t *observer, const ecu_tuning_t *tuning, const double z_tilde[NZ],
                               double g[NZ]) {
  double limit = innovation_limit(observer, tuning);
  double scale = limit == 0.0 ? 0.0 : fmax(fabs(z_tilde[1]), fabs(z_tilde[2])) / limit;
  for (int i = 0; i < NZ; i++) g[i] = scale > 1.0 ? z_tilde[i] / scale : z_tilde[i];
}

/* PersistentInnovationBound.advance: count the step whose innovation the bound just limited
 * (the larger lateral entry's sign, vy on a tie); a step within it or a new sign restarts,
 * and so does a step whose lateral acceleration is not below the gate (a manoeuvre). */
static void advance_bound(ecu_observer_t *observer, const ecu_tuning_t *tuning, const double z_tilde[NZ],
                          double lateral_accel) {
  if (tuning->eso_innovation_persistence == 0.0 || tuning->eso_innovation_limit == 0.0) return;
  double gate = tuning->eso_widening_lateral_accel;
  if (gate > 0.0 && !(fabs(lateral_accel) < gate)) { /* NaN: not below */
    restart_bound(observer);
    return;
  }
  double peak = fabs(z_tilde[2]) > fabs(z_tilde[1]) ? z_tilde[2] : z_tilde[1];
  if (!(fabs(peak) / innovation_limit(observer, tuning) > 1.0)) { /* NaN: not > 1 */
    restart_bound(observer);
    return;
  }
  double sign = peak > 0.0 ? 1.0 : -1.0;
  if (sign == observer->saturated_sign)
    observer->saturated_steps += observer->saturated_steps < SATURATED_STEPS_MAX ? 1 : 0;
  else
    observer->saturated_steps = 1;
  observer->saturated_sign = sign;
}

void ecu_observer_bias_update(ecu_observer_t *observer, const ecu_tuning_t *tuning, double ts,
                              const ecu_sample_t *sample) {
  double yaw = sample->yaw, rate = sample->yaw_rate;
  if (!(isfinite(yaw) && isfinite(rate))) {
    observer->has_bias_previous = 0;
    return;
  }
  if (observer->has_bias_previous) {
    double heading_rate = remainder(yaw - observer->bias_previous_yaw, TWO_PI) / ts;
    double residual = 0.5 * (rate + observer->bias_previous_rate) - heading_rate;
    double bias = observer->yaw_rate_bias + (1.0 - tuning->yaw_rate_bias_pole) * (residual - observer->yaw_rate_bias);
    if (isfinite(bias)) observer->yaw_rate_bias = bias;
  }
  observer->bias_previous_yaw = yaw;
  observer->bias_previous_rate = rate;
  observer->has_bias_previous = 1;
}

void ecu_observer_disturbance(ecu_observer_t *observer, const ecu_tuning_t *tuning, const double z[NZ],
                              double w[NZ]) {
  double beta2 = -(1.0 - tuning->eso_pole) * (1.0 - tuning->eso_second_pole), z_tilde[NZ], g[NZ];
  if (!observer->running) {
    memcpy(observer->z_hat, z, sizeof observer->z_hat);
    memset(observer->w_hat, 0, sizeof observer->w_hat);
    restart_bound(observer);
    observer->running = 1;
    observer->reset = 1;
    memset(w, 0, NZ * sizeof(double));
    return;
  }
  for (int i = 0; i < NZ; i++) z_tilde[i] = z[i] - observer->z_hat[i];
  memcpy(w, observer->w_hat, NZ * sizeof(double));
  if (!isfinite(ecu_dot(z_tilde, z_tilde, NZ))) return;
  bounded_innovation(observer, tuning, z_tilde, g);
  double next[NZ];
  for (int i = 0; i < NZ; i++) next[i] = observer->w_hat[i] - beta2 * g[i];
  if (isfinite(ecu_dot(next, next, NZ))) memcpy(w, next, sizeof next);
}

void ecu_observer_update(ecu_observer_t *observer, const ecu_tuning_t *tuning, const ecu_local_model_t *model,
                         const double z[NZ], double torque, double steer) {
  double c = tuning->eso_pole + tuning->eso_second_pole - 1.0;
  double beta2 = -(1.0 - tuning->eso_pole) * (1.0 - tuning->eso_second_pole);
  double u[2] = {torque, steer}, z_tilde[NZ], g[NZ], next_z[NZ], next_w[NZ];
  const double *z_hat = observer->z_hat, *w_hat = observer->w_hat;
  for (int i = 0; i < NZ; i++) z_tilde[i] = z[i] - z_hat[i];
  bounded_innovation(observer, tuning, z_tilde, g);
  double check = ecu_dot(z_hat, z_hat, NZ) + ecu_dot(w_hat, w_hat, NZ) + ecu_dot(u, u, 2) +
                 2.0 * ecu_dot(z_tilde, z_tilde, NZ);
  if (!isfinite(check)) {
    observer->running = 0;
    return;
  }
  for (int i = 0; i < NZ; i++) {
    double sum = w_hat[i] + model->offset[i];
    for (int j = 0; j < NZ; j++) {
      double beta1 = (i == j ? c : 0.0) - model->A[i][j];
      sum += model->A[i][j] * z_hat[j] - beta1 * z_tilde[j];
    }
    for (int j = 0; j < ECU_NU; j++) sum += model->B[i][j] * u[j];
#if ECU_BILINEAR
    sum += steer * ecu_dot(model->N[i], z, NZ);
#endif
    next_z[i] = sum;
    next_w[i] = w_hat[i] - beta2 * g[i];
  }
  if (!isfinite(ecu_dot(next_z, next_z, NZ) + ecu_dot(next_w, next_w, NZ))) {
    observer->running = 0;
    return;
  }
  memcpy(observer->z_hat, next_z, sizeof observer->z_hat);
  memcpy(observer->w_hat, next_w, sizeof observer->w_hat);
  advance_bound(observer, tuning, z_tilde, z[0] * z[2]); /* vx r, as EsoDkmpc._after_command */
}

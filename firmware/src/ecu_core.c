/*
 * The control step of the steering MPCs (see ecu_core.h), a port of the Python controllers:
 *   controller/mpc_base.py     step, fallback (shifted previous plan), final guard
 *   controller/qp_mpc.py       the plan: affine state prediction, pose linearisation, QP
 *   controller/reference.py    path progress and the pose reference over the horizon
 * with the prediction of ecu_predict.c (lifted_mpc.py, eso_dkmpc.py, lmpc.py), the
 * observers of ecu_observer.c, the grip envelope of ecu_grip.c (grip_envelope.py) and the
 * QP of ecu_qp.c. Quantities keep the Python names; array shapes are in the comments.
 * Nothing is allocated, so a step's time is bounded by its loops.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "ecu_core.h"
#include "ecu_path_search.h"
#include "ecu_predict.h"
#include "ecu_pyfloat.h"
#include "ecu_steady_slip.h"
#include "os.h"

#define NP ECU_NP_MAX
#define NC ECU_NC_MAX
#define STEER_LIMIT 0.3           /* rad: controller.base.STEER_LIMIT_RAD */
#define TWO_PI 6.283185307179586  /* 2.0 * math.pi */
#define PI 3.141592653589793 /* math.pi */
#define CONTROL_PERIOD 0.025     /* s: controller.base.CONTROL_PERIOD_S, the grip estimate's Ts */

static double clamp(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

size_t ecu_core_size(void) { return sizeof(ecu_core_t); }

const char *ecu_build_shapes(void) {
  static char text[256];
  static const int widths[] = ECU_LAYER_WIDTHS;
  snprintf(text, sizeof text,
           "n_x %d, n_u %d, n_z %d, dictionary %d, knots %d, form %d, encoder %d layers (last %d), "
           "Np/Nc eso-dkmpc %d/%d dkmpc %d/%d lmpc %d/%d",
           ECU_NX, ECU_NU, ECU_NZ, ECU_NDICT, ECU_NK, ECU_FORM, ECU_N_LAYERS,
           widths[ECU_N_LAYERS > 0 ? ECU_N_LAYERS - 1 : 0], /* {0} without layers */
           ECU_NP_ESO_DKMPC, ECU_NC_ESO_DKMPC, ECU_NP_DKMPC, ECU_NC_DKMPC, ECU_NP_LMPC, ECU_NC_LMPC);
  return text;
}

/* ------------------------------------------------------------------ start-up */
/* The heading target's fields, with controller.tuning's rules and message: 0, or -1 with
 * the field named in err. */
static int check_slip_fields(const char *data_path, const char *name, const ecu_tuning_t *t, char *err,
                             size_t err_len) {
  const double limit = t->slip_target_limit, gate = t->slip_target_gate;
  const struct {
    const char *name, *rule;
    double value;
    int ok;
  } fields[2] = {{"slip_target_limit", "must be in [0, 0.2] rad (0: off)", limit, limit >= 0.0 && limit <= 0.2},
                 {"slip_target_gate", "must be in (0, 1] rad", gate, gate > 0.0 && gate <= 1.0}};
  for (int i = 0; i < 2; i++) {
    if (fields[i].ok) continue;
    char got[32];
    py_repr(got, sizeof got, fields[i].value);
    snprintf(err, err_len, "%s: [%s] %s %s, got %s", data_path, name, fields[i].name, fields[i].rule, got);
    return -1;
  }
  return 0;
}

int ecu_core_load(ecu_core_t *core, const char *data_path, const char *name, char *err, size_t err_len) {
  static const char *const NAMES[ECU_N_CONTROLLERS] = {"eso-dkmpc", "dkmpc", "lmpc"};
  int id = -1;
  for (int i = 0; i < ECU_N_CONTROLLERS; i++)
    if (name && strcmp(name, NAMES[i]) == 0) id = i;
  if (id < 0) {
    snprintf(err, err_len, "unknown controller %s; the C core has eso-dkmpc, dkmpc, lmpc", name ? name : "(null)");
    return -1;
  }
  core->loaded = 0;
  if (ecu_read_data(data_path, &core->cfg, err, err_len) != 0) return -1;
  const ecu_tuning_t *t = &core->cfg.tuning[id];
  if (id == ECU_ESO_DKMPC && !(t->eso_pole >= 0.0 && t->eso_pole < 1.0 && t->eso_second_pole >= 0.0 &&
                               t->eso_second_pole < 1.0 && isfinite(t->disturbance_decay) &&
                               t->eso_innovation_limit >= 0.0 && t->eso_innovation_limit <= 10.0 &&
                               t->eso_innovation_persistence >= 0.0 && t->eso_innovation_persistence <= 1000.0 &&
                               t->eso_widening_lateral_accel >= 0.0 && t->eso_widening_lateral_accel <= 20.0 &&
                               t->yaw_rate_bias_pole >= 0.0 && t->yaw_rate_bias_pole <= 1.0)) {
    snprintf(err, err_len, "%s: [eso-dkmpc] eso_pole, eso_second_pole must be in [0, 1), "
             "disturbance_decay finite, eso_innovation_limit in [0, 10], eso_innovation_persistence in [0, 1000], "
             "eso_widening_lateral_accel in [0, 20] and yaw_rate_bias_pole in [0, 1]",
             data_path);
    return -1;
  }
  if (check_slip_fields(data_path, NAMES[id], t, err, err_len) != 0) return -1;
  if (ecu_qp_init(&core->qp, id, t, err, err_len) != 0) return -1;
  core->controller = id;
  core->tun = t;
  core->n_pred = t->n_pred;
  core->n_ctrl = t->n_ctrl;
  for (int i = 0; i < core->n_pred; i++) core->decay_power[i] = pow(t->disturbance_decay, (double)i);
  ecu_grip_init(&core->grip, t, &core->cfg, CONTROL_PERIOD); /* exp once, here */
  core->model.valid = 0; /* the per-speed matrices of this data file from the first step */
  core->path_n = 0;
  core->loaded = 1;
  ecu_core_reset(core);
  return 0;
}

void ecu_core_unload(ecu_core_t *core) {
  core->loaded = 0;
  ecu_qp_release(&core->qp);
}

int ecu_core_set_path(ecu_core_t *core, const double *x, const double *y, const double *yaw, const double *s,
                      int n, char *err, size_t err_len) {
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
  memcpy(core->path_x, x, (size_t)n * sizeof(double));
  memcpy(core->path_y, y, (size_t)n * sizeof(double));
  memcpy(core->path_yaw, yaw, (size_t)n * sizeof(double));
  memcpy(core->path_s, s, (size_t)n * sizeof(double));
  core->path_n = n;
  core->has_progress = 0;
  return 0;
}

int ecu_core_select_path(ecu_core_t *core, const ecu_path_pool_t *paths, int path_id, char *err, size_t err_len) {
  ecu_path_view_t path;
  if (ecu_paths_find(paths, path_id, &path) != 0) {
    snprintf(err, err_len, "PATH_ID %d is not loaded", path_id);
    return -1;
  }
  return ecu_core_set_path(core, path.x, path.y, path.yaw, path.s, path.n, err, err_len);
}

int ecu_core_path_copy(const ecu_core_t *core, double *x, double *y, double *yaw, double *s, int max) {
  int n = core->path_n < max ? core->path_n : max;
  memcpy(x, core->path_x, (size_t)n * sizeof(double));
  memcpy(y, core->path_y, (size_t)n * sizeof(double));
  memcpy(yaw, core->path_yaw, (size_t)n * sizeof(double));
  memcpy(s, core->path_s, (size_t)n * sizeof(double));
  return core->path_n;
}

void ecu_core_reset(ecu_core_t *core) {
  core->has_plan = 0;
  core->plan_age = 0;
  core->has_last = 0;
  core->has_progress = 0;
  core->history_n = 0;
  core->prepared = 0;
  ecu_observer_reset(&core->observer);
  ecu_grip_reset(&core->grip);
  core->yaw_rate_bound = INFINITY;
}

/* ------------------------------------------------------------------ reference */
/* numpy.interp(v, path_s, values) inside the path (ends held), for x, y and yaw at once:
 * one search for the three (out[3]). */
static void interp_pose(const ecu_core_t *core, double v, double out[3]) {
  const double *path_s = core->path_s;
  const int path_n = core->path_n;
  const double *values[3] = {core->path_x, core->path_y, core->path_yaw};
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
static void horizon_reference(const ecu_core_t *core, double vx, double vehicle_yaw, double reference[][3]) {
  const double *path_x = core->path_x, *path_y = core->path_y, *path_yaw = core->path_yaw, *path_s = core->path_s;
  const int path_n = core->path_n, n_pred = core->n_pred;
  double advance = fmax(vx, 0.0) * core->cfg.ts;
  for (int i = 0; i < n_pred; i++) {
    double s = core->progress + advance * (double)(i + 1);
    double *pose = reference[i];
    interp_pose(core, s, pose);
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

/* ------------------------------------------------------------------ the step */
typedef struct {
  int status, iterations;
  double steer[NC], cost, solve_time_s, slack_max;
} plan_t;

static double previous_steer(const ecu_core_t *core, const ecu_sample_t *sample) {
  return core->has_last ? core->last_steer : clamp(sample->steer_angle, -STEER_LIMIT, STEER_LIMIT);
}

/* SteeringMpc.shifted_plan: the last good plan shifted to now, else the previous steer held. */
static void shifted_plan(const ecu_core_t *core, const ecu_sample_t *sample, double nominal[NC]) {
  const int n_ctrl = core->n_ctrl;
  for (int c = 0; c < n_ctrl; c++) {
    int from = core->plan_age + 1 + c;
    nominal[c] = !core->has_plan ? previous_steer(core, sample) : core->plan_steer[from < n_ctrl ? from : n_ctrl - 1];
  }
}

/* ObservedMpc.target_reference: the reference's heading (Np,) moved by the steady side slip
 * of the step's estimate, bounded and faded out as the horizon's reference bends. */
static void target_reference(const ecu_core_t *core, const ecu_sample_t *sample, double reference[][3]) {
  const ecu_tuning_t *t = core->tun;
  if (t->slip_target_limit == 0.0) return; /* off: no bend to measure (the target would be 0) */
  double bend = ecu_reference_bend(&reference[0][2], core->n_pred, 3);
  double target = ecu_slip_target(ecu_measured_slip(sample->vy, sample->vx), bend, t->slip_target_limit,
                                  t->slip_target_gate);
  if (target != 0.0)
    for (int i = 0; i < core->n_pred; i++) reference[i][2] -= target;
}

/* QpSteeringMpc.predict_states of the core's controller into core->free, core->gain. */
static void predict(ecu_core_t *core, const ecu_sample_t *sample, double torque) {
  if (core->controller == ECU_LMPC) {
    ecu_predict_bicycle(&core->cfg, core->tun, sample, core->free, core->gain, &core->basis);
  } else {
    ecu_observer_t *observer = core->controller == ECU_ESO_DKMPC ? &core->observer : NULL;
    ecu_predict_koopman(&core->cfg, core->tun, observer, core->decay_power, sample, torque, &core->model,
                        core->lifted, core->free, core->gain, &core->basis);
  }
}

/* models.measurement.wrap_angle: to [-pi, pi), values inside unchanged bit for bit. */
static double wrap_angle(double a) { return (a >= -PI && a < PI) ? a : py_mod(a + PI, TWO_PI) - PI; }

/* SteeringMpc.step's grip estimate (the envelope's bound from the measured sample, just
 * before _prepare), then QpSteeringMpc._prepare: with delay compensation on, predict once
 * from the measured sample, move the prediction's start over the window and return (in
 * planned) the sample at the window's end; planned = *sample otherwise. */
static void prepare(ecu_core_t *core, const ecu_sample_t *sample, double torque, ecu_sample_t *planned) {
  *planned = *sample;
  core->prepared = 0;
  /* The grip estimate reads the measurement, as the observer does, before any delay shift. */
  core->yaw_rate_bound = ecu_grip_update(&core->grip, sample);
  const double delay = ecu_total_delay(core->tun->delay_compensation_s, core->sample_age_s);
  if (delay <= 0.0) return;
  double (*free)[3] = core->free, (*gain)[3][NC] = core->gain;
  const int n_pred = core->n_pred, n_ctrl = core->n_ctrl;
  predict(core, sample, torque);
  core->prepared = 1;
  double sum = 0.0;
  for (int i = 0; i <= n_pred; i++)
    for (int x = 0; x < 3; x++) {
      sum += free[i][x];
      for (int c = 0; c < n_ctrl; c++) sum += gain[i][x][c];
    }
  if (!isfinite(sum)) return; /* make_plan falls back on it */
  ecu_delay_window_t window;
  const double first = previous_steer(core, sample);
  ecu_delay_window(delay, core->cfg.ts, core->history_n ? core->history : &first, core->history_n ? core->history_n : 1,
                   &window);
  const int last = window.whole_steps;
  double in_flight[NC], states[ECU_COMMAND_HISTORY + 1][3], pose[3];
  for (int c = 0; c < n_ctrl; c++) in_flight[c] = window.inputs[c < last ? c : last];
  for (int j = 0; j <= last + 1; j++)
    for (int x = 0; x < 3; x++) states[j][x] = free[j][x] + ecu_dot(gain[j][x], in_flight, n_ctrl);
  const double pose0[3] = {sample->x, sample->y, sample->yaw};
  ecu_pose_after(pose0, states, core->cfg.ts, &window, core->tun->pose_heading_advance, pose);
  double moved[3];
  for (int x = 0; x < 3; x++) moved[x] = states[last][x] + window.fraction * (states[last + 1][x] - states[last][x]);
  if (core->controller == ECU_LMPC) ecu_shift_bicycle(&core->basis, &window, n_pred, free);
  else ecu_shift_koopman(&core->model, &core->basis, core->lifted, &window, n_pred, free);
  planned->vx = moved[0];
  planned->vy = moved[1];
  planned->yaw_rate = moved[2];
  planned->x = pose[0];
  planned->y = pose[1];
  planned->yaw = wrap_angle(pose[2]);
}

/* QpSteeringMpc._plan; fills the predictions of out. */
static void make_plan(ecu_core_t *core, const ecu_sample_t *sample, double torque, plan_t *plan, ecu_output_t *out) {
  double (*free)[3] = core->free, (*gain)[3][NC] = core->gain, (*nominal_states)[3] = core->nominal_states;
  double (*poses)[3] = core->poses, (*jac)[3][NC] = core->jac, (*pose_offset)[3] = core->pose_offset;
  double (*reference)[3] = core->reference;
  const int n_pred = core->n_pred, n_ctrl = core->n_ctrl;
  double nominal[NC], sum = 0.0;
  ecu_qp_solution_t solution;
  memset(plan, 0, sizeof *plan);
  target_reference(core, sample, reference);
  if (!core->prepared) predict(core, sample, torque);
  core->prepared = 0;
  shifted_plan(core, sample, nominal);
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
  ecu_linearise_pose(core->cfg.ts, core->tun, sample, nominal_states, gain, poses, jac);
  for (int i = 0; i < n_pred; i++)
    for (int x = 0; x < 3; x++) {
      double s = 0.0;
      for (int c = 0; c < n_ctrl; c++) s += jac[i][x][c] * nominal[c];
      pose_offset[i][x] = poses[i][x] - s - reference[i][x];
    }
  /* The QP's arrays are (Np * 3, Nc) row-major: jac, and gain / free of steps 1..Np. */
  int64_t start = os_monotonic_ns();
  ecu_qp_solve(&core->qp, sample->vx, &jac[0][0][0], &pose_offset[0][0], previous_steer(core, sample), &gain[1][0][0],
               &free[1][0], nominal, core->yaw_rate_bound, &solution);
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
static void finish(ecu_core_t *core, double steer, double torque, ecu_output_t *out) {
  core->last_steer = isfinite(steer) ? clamp(steer, -STEER_LIMIT, STEER_LIMIT) : 0.0;
  core->last_torque = isfinite(torque) ? clamp(torque, core->cfg.torque_min, core->cfg.torque_max) : 0.0;
  core->has_last = 1;
  if (core->history_n == ECU_COMMAND_HISTORY) { /* the oldest goes */
    memmove(core->history, core->history + 1, (ECU_COMMAND_HISTORY - 1) * sizeof core->history[0]);
    core->history_n--;
  }
  core->history[core->history_n++] = core->last_steer;
  out->steer_angle = core->last_steer;
  out->drive_torque = core->last_torque;
}

/* SteeringMpc._after_command: the observer advances with the command the vehicle got. */
static void after_command(ecu_core_t *core) {
  if (core->controller == ECU_ESO_DKMPC)
    ecu_observer_update(&core->observer, core->tun, &core->model, core->lifted, core->last_torque, core->last_steer);
}

/* SteeringMpc._fallback (+ ObservedMpc's restart): the shifted previous plan, else the
 * previous command. torque NAN: none computed (invalid sample); sample_valid: hooks run. */
static void fallback(ecu_core_t *core, int status, double torque, const plan_t *plan, int sample_valid,
                     ecu_output_t *out) {
  double steer;
  if (core->controller == ECU_ESO_DKMPC && !sample_valid) core->observer.running = 0;
  if (core->has_plan && core->plan_age + 1 < core->n_ctrl) {
    core->plan_age++;
    steer = core->plan_steer[core->plan_age];
  } else {
    core->has_plan = 0;
    steer = core->has_last ? core->last_steer : 0.0;
  }
  if (!sample_valid) torque = core->has_last ? core->last_torque : 0.0;
  finish(core, steer, torque, out);
  if (sample_valid) after_command(core);
  out->status = status;
  out->fallback = 1;
  out->iterations = plan ? plan->iterations : 0;
  out->solve_time_s = plan ? plan->solve_time_s : 0.0;
  out->cost = NAN;
  out->slack_max = 0.0;
  out->n_pred = 0;
  out->observer_reset = core->observer.reset;
  core->observer.reset = 0;
}

static void step_body(ecu_core_t *core, const ecu_sample_t *measured, ecu_output_t *out) {
  const ecu_config_t *cfg = &core->cfg;
  ecu_sample_t corrected = *measured;
  const ecu_sample_t *sample = &corrected;
  const double *values = &sample->vx;
  int finite = 1;
  plan_t plan;
  memset(out, 0, offsetof(ecu_output_t, predicted_pose));
  out->cost = NAN;
  for (int i = 0; i < 9; i++) finite = finite && isfinite(values[i]);
  if (!core->loaded) { /* no data: the safe command, never a crash */
    out->status = ECU_NOT_RUN;
    out->fallback = 1;
    return;
  }
  if (core->controller == ECU_ESO_DKMPC) { /* ObservedMpc.step: the yaw rate corrected by its bias */
    ecu_observer_bias_update(&core->observer, core->tun, cfg->ts, measured);
    double bias = core->observer.yaw_rate_bias;
    if (bias != 0.0) corrected.yaw_rate = measured->yaw_rate - bias;
  }
  if (core->path_n < 2 || !finite) {
    fallback(core, ECU_NOT_RUN, NAN, NULL, 0, out);
    return;
  }
  double torque = clamp(cfg->speed_gain * (sample->target_speed - sample->vx), cfg->torque_min, cfg->torque_max);
  ecu_sample_t planned;
  prepare(core, sample, torque, &planned);
  sample = &planned;
  /* progress only: the control law takes the lateral error from the reference poses */
  ecu_path_track(core->path_x, core->path_y, core->path_s, core->path_n, sample->x, sample->y, &core->progress,
                 &core->has_progress);
  horizon_reference(core, sample->vx, sample->yaw, core->reference);
  core->observer.reset = 0;
  make_plan(core, sample, torque, &plan, out);
  const int n_ctrl = core->n_ctrl;
  double steer_sum = 0.0;
  for (int c = 0; c < n_ctrl; c++) steer_sum += plan.steer[c];
  if (!(plan.status == ECU_SOLVED || plan.status == ECU_SOLVED_INACCURATE) || !isfinite(steer_sum) ||
      !isfinite(plan.cost)) {
    fallback(core, plan.status, torque, &plan, 1, out);
    return;
  }
  for (int c = 0; c < n_ctrl; c++) core->plan_steer[c] = clamp(plan.steer[c], -STEER_LIMIT, STEER_LIMIT);
  core->has_plan = 1;
  core->plan_age = 0;
  finish(core, core->plan_steer[0], torque, out);
  after_command(core);
  out->status = plan.status;
  out->iterations = plan.iterations;
  out->solve_time_s = plan.solve_time_s;
  out->cost = plan.cost;
  out->slack_max = plan.slack_max;
  out->fallback = 0;
  out->observer_reset = core->observer.reset;
}

void ecu_core_step_aged(ecu_core_t *core, const ecu_sample_t *sample, double sample_age_s, ecu_output_t *out) {
  int64_t start = os_monotonic_ns();
  core->sample_age_s = sample_age_s;
  step_body(core, sample, out);
  out->step_time_s = 1e-9 * (double)(os_monotonic_ns() - start);
}

void ecu_core_step(ecu_core_t *core, const ecu_sample_t *sample, ecu_output_t *out) {
  ecu_core_step_aged(core, sample, 0.0, out);
}

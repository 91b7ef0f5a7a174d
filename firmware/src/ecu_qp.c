/*
 * The condensed steering QP of eq. 15 (a port of controller/steering_qp.py) on the
 * solvers OSQP generated at build time (build/firmware/gen/qp, ECU_QP_WORKSPACES workspaces
 * per controller, embedded mode 2), through OSQP's public API only. The sparsity is fixed by
 * the generator; each step writes the values in the same column order as the Python
 * SteeringQp and updates them in place.
 *
 * Variables v = [U (Nc steer angles), s (3 slacks)]. Constraints, in row order: the Nc
 * steer bounds, the 3 slack bounds s >= 0, then per soft-constrained prediction step and
 * state an upper row (gain U - s <= max - free) and a lower row (gain U + s >= min - free).
 * The soft steps and states are SteeringQp's (controller.steering_qp.soft_state_rows:
 * the first ECU_SOFT_LEADING_STEPS steps, every ECU_SOFT_STRIDE-th step and the last, the
 * states of ECU_SOFT_STATE_MASK; all generated into ecu_build.h from SOFT_LEADING_STEPS,
 * SOFT_STEP_STRIDE and SOFT_STATES). A's U column c holds
 * the gain's causal entries only, the rows of the steps i > c (SteeringQp's pattern: the
 * entries of c >= i are zero). With qp_steer_rate_limit > 0, Nc rate rows follow the soft
 * rows: row j bounds U_j - U_{j-1} (U_{-1} the previous command: row 0's bounds move).
 * Where the grip envelope gives a finite yaw-rate bound (ecu_grip.h), the yaw-rate rows'
 * bounds of that solve are narrowed to within +-bound (SteeringQp.solve's yaw_rate_bound).
 */
#include <math.h>
#include <string.h>
#include <stdio.h>

#include "ecu_qp.h"
#include "qp_workspaces.h" /* the generated solvers and the nonzeros of their A */

#define N_SOFT ECU_QP_N_SOFT
#define YAW_RATE_STATE 2 /* the yaw rate's index in [vx, vy, yaw_rate] (steering_qp.YAW_RATE_STATE) */
#define STEER_LIMIT 0.3 /* rad, eq. 22 (controller.base.STEER_LIMIT_RAD) */
#define CONTROL_PERIOD 0.025 /* s, Ts of the rate rows (controller.base.CONTROL_PERIOD_S) */
#define NP ECU_NP_MAX
#define NC ECU_NC_MAX
#if ECU_SOFT_STRIDE < 1 || ECU_SOFT_LEADING_STEPS < 0 || (ECU_SOFT_STATE_MASK & ~7)
#error "ecu_build.h: ECU_SOFT_STRIDE must be >= 1, ECU_SOFT_LEADING_STEPS >= 0 and ECU_SOFT_STATE_MASK within [vx, vy, yaw_rate]"
#endif

/* The generated workspaces are the process's, whichever core holds one: who holds each
 * (NULL: free) and the rho it was generated with (0: not yet read), so that a core taking
 * it starts the solver afresh. */
static const ecu_qp_t *holder[ECU_N_CONTROLLERS][ECU_QP_WORKSPACES];
static double initial_rho[ECU_N_CONTROLLERS][ECU_QP_WORKSPACES];

void ecu_qp_release(ecu_qp_t *qp) {
  if (qp->solver && holder[qp->controller][qp->workspace] == qp) holder[qp->controller][qp->workspace] = NULL;
  qp->solver = NULL;
}

/* qp's own workspace of controller, else the first free one; -1 when all are held. */
static int take_workspace(ecu_qp_t *qp, int controller) {
  if (qp->solver && qp->controller == controller && holder[controller][qp->workspace] == qp) return qp->workspace;
  ecu_qp_release(qp);
  for (int k = 0; k < ECU_QP_WORKSPACES; k++) {
    if (!holder[controller][k]) {
      holder[controller][k] = qp;
      return k;
    }
  }
  return -1;
}

int ecu_qp_init(ecu_qp_t *qp, int controller, const ecu_tuning_t *tuning, char *err, size_t err_len) {
  static const char *const NAMES[ECU_N_CONTROLLERS] = {"eso-dkmpc", "dkmpc", "lmpc"};
  OSQPSolver *const solvers[ECU_N_CONTROLLERS][ECU_QP_WORKSPACES] = ECU_QP_WORKSPACE_TABLE;
  static const int GENERATED_A_NNZ[ECU_N_CONTROLLERS] = ECU_QP_A_NNZ_TABLE;
  OSQPSettings settings;
  int workspace = take_workspace(qp, controller);
  if (workspace < 0) {
    snprintf(err, err_len, "all %d generated QP workspaces of %s are held by other cores", ECU_QP_WORKSPACES,
             NAMES[controller]);
    return -1;
  }
  OSQPSolver *const solver = solvers[controller][workspace];
  qp->solver = solver;
  qp->controller = controller;
  qp->workspace = workspace;
  qp->tuning = tuning;
  const int n_pred = qp->n_pred = tuning->n_pred;
  const int n_ctrl = qp->n_ctrl = tuning->n_ctrl;
  double *const p_data = qp->p_data, *const a_data = qp->a_data, *const q = qp->q;
  double *const lower = qp->lower, *const upper = qp->upper;
  int *const soft_row = qp->soft_row, *const soft_count = qp->soft_count, *const a_column = qp->a_column;
  /* A reload starts the solver afresh: rho back to its generated value (the rest of the
   * solver's state is rewritten by the first step's update and warm start). */
  double *rho = &initial_rho[controller][workspace];
  if (*rho == 0.0) *rho = solver->settings->rho;
  else if (osqp_update_rho(solver, *rho) != 0) {
    snprintf(err, err_len, "OSQP refused to restore rho %g", *rho);
    return -1;
  }
  settings = *solver->settings;
  settings.max_iter = tuning->max_iter;
  settings.eps_abs = tuning->eps_abs;
  settings.eps_rel = tuning->eps_rel;
  if (osqp_update_settings(solver, &settings) != 0) {
    snprintf(err, err_len, "OSQP refused the tuning's settings (max_iter %d, eps_abs %g, eps_rel %g)",
             tuning->max_iter, tuning->eps_abs, tuning->eps_rel);
    return -1;
  }
  /* p D'D, D the increment operator (U_j - U_{j-1}); r I is added per step (use_weights). */
  memset(qp->fixed_hessian, 0, sizeof qp->fixed_hessian);
  for (int j = 0; j < n_ctrl; j++) {
    qp->rate_diagonal[j] = tuning->p_steer_rate * (j + 1 < n_ctrl ? 2.0 : 1.0);
    if (j + 1 < n_ctrl) qp->fixed_hessian[j][j + 1] = qp->fixed_hessian[j + 1][j] = -tuning->p_steer_rate;
  }
  /* The parts of P, A, q, l, u that never change. */
  int upper_count = n_ctrl * (n_ctrl + 1) / 2;
  for (int k = 0; k < N_SOFT; k++) p_data[upper_count + k] = 2.0 * tuning->slack_l2;
  int n_soft_rows = 0;
  for (int k = 0; k < N_SOFT; k++) soft_count[k] = 0;
  for (int i = 0; i < n_pred; i++) {
    /* soft_steps: the leading steps, every stride-th step, the last. */
    if (i >= ECU_SOFT_LEADING_STEPS && (i + 1) % ECU_SOFT_STRIDE != 0 && i != n_pred - 1) continue;
    for (int k = 0; k < N_SOFT; k++) {
      if (!(ECU_SOFT_STATE_MASK & (1 << k))) continue;
      soft_row[n_soft_rows++] = N_SOFT * i + k;
      soft_count[k]++;
    }
  }
  qp->max_steer_step = tuning->qp_steer_rate_limit * CONTROL_PERIOD;
  const int n_rate_rows = qp->n_rate_rows = qp->max_steer_step > 0.0 ? n_ctrl : 0;
  a_column[0] = 0;
  for (int j = 0; j < n_ctrl; j++) {
    /* The first soft row whose step the input of step j reaches (the causal entries). */
    int first = 0, step_row = N_SOFT * (j < n_pred ? j : n_pred);
    while (first < n_soft_rows && soft_row[first] < step_row) first++;
    qp->gain_first[j] = first;
    /* After the gain entries: +1 in rate row j, -1 in rate row j + 1 (when there are). */
    const int rate_entries = n_rate_rows == 0 ? 0 : (j + 1 < n_rate_rows ? 2 : 1);
    const int rate_at = a_column[j] + 1 + 2 * (n_soft_rows - first);
    if (rate_entries > 0) a_data[rate_at] = 1.0;
    if (rate_entries > 1) a_data[rate_at + 1] = -1.0;
    a_column[j + 1] = rate_at + rate_entries;
    a_data[a_column[j]] = 1.0;
  }
  qp->n_soft_rows = n_soft_rows;
  int a_count = a_column[n_ctrl];
  for (int k = 0; k < N_SOFT; k++) a_count += 1 + 2 * soft_count[k];
  qp->a_count = a_count;
  /* The generated solver must have this pattern (it is generated from SteeringQp). */
  if (a_count != GENERATED_A_NNZ[controller]) {
    snprintf(err, err_len, "the generated QP's A has %d nonzeros, the C core writes %d (regenerate: make firmware)",
             GENERATED_A_NNZ[controller], a_count);
    return -1;
  }
  /* Slack column k: its bound row, then state k's soft rows (upper -1, lower +1). */
  double *col = a_data + a_column[n_ctrl];
  for (int k = 0; k < N_SOFT; k++) {
    col[0] = 1.0;
    for (int i = 0; i < soft_count[k]; i++) {
      col[1 + 2 * i] = -1.0;
      col[2 + 2 * i] = 1.0;
    }
    col += 1 + 2 * soft_count[k];
  }
  for (int j = 0; j < n_ctrl; j++) {
    q[j] = 0.0;
    lower[j] = -STEER_LIMIT;
    upper[j] = STEER_LIMIT;
  }
  int soft_first = n_ctrl + N_SOFT;
  for (int k = 0; k < N_SOFT; k++) {
    q[n_ctrl + k] = tuning->slack_l1;
    lower[n_ctrl + k] = 0.0;
    upper[n_ctrl + k] = OSQP_INFTY;
  }
  for (int r = 0; r < n_soft_rows; r++) {
    lower[soft_first + 2 * r] = -OSQP_INFTY;
    upper[soft_first + 2 * r + 1] = OSQP_INFTY;
  }
  qp->rate_first = soft_first + 2 * n_soft_rows;
  for (int r = 0; r < n_rate_rows; r++) { /* row 0 is moved by the previous command per step */
    lower[qp->rate_first + r] = -qp->max_steer_step;
    upper[qp->rate_first + r] = qp->max_steer_step;
  }
  memset(qp->warm, 0, sizeof qp->warm);
  memset(qp->initial_dual, 0, sizeof qp->initial_dual);
  for (int k = 0; k < N_SOFT; k++) qp->initial_dual[n_ctrl + k] = -tuning->slack_l1;
  qp->constraints_were_active = 0;
  return 0;
}

static int map_status(OSQPInt status) {
  switch (status) {
    case OSQP_SOLVED: return ECU_SOLVED;
    case OSQP_SOLVED_INACCURATE: return ECU_SOLVED_INACCURATE;
    case OSQP_MAX_ITER_REACHED: return ECU_MAX_ITERATIONS;
    case OSQP_PRIMAL_INFEASIBLE:
    case OSQP_PRIMAL_INFEASIBLE_INACCURATE:
    case OSQP_DUAL_INFEASIBLE:
    case OSQP_DUAL_INFEASIBLE_INACCURATE: return ECU_INFEASIBLE;
    default: return ECU_NUMERICAL_ERROR;
  }
}

/* MpcTuning.weights_at and SteeringQp._use_weights: the pose weights and r I + p D'D at
 * measured speed vx, the same arithmetic as the Python (bit-identical weights). */
static void use_weights(ecu_qp_t *qp, double vx) {
  const ecu_tuning_t *tun = qp->tuning;
  const int n_pred = qp->n_pred, n_ctrl = qp->n_ctrl;
  const double blend = fmin(fmax((vx - tun->schedule_low) / (tun->schedule_high - tun->schedule_low), 0.0), 1.0);
  const double q_position = tun->low_q_position + blend * (tun->q_position - tun->low_q_position);
  const double q_yaw = tun->low_q_yaw + blend * (tun->q_yaw - tun->low_q_yaw);
  const double r_steer = tun->low_r_steer + blend * (tun->r_steer - tun->low_r_steer);
  for (int j = 0; j < n_ctrl; j++) qp->fixed_hessian[j][j] = r_steer + qp->rate_diagonal[j];
  for (int i = 0; i < n_pred; i++) {
    qp->pose_weight[3 * i] = qp->pose_weight[3 * i + 1] = q_position;
    qp->pose_weight[3 * i + 2] = q_yaw;
  }
}

void ecu_qp_solve(ecu_qp_t *qp, double vx, const double *jac, const double *pose_offset, double previous_steer,
                  const double *gain, const double *free_states, const double *warm_steer, double yaw_rate_bound,
                  ecu_qp_solution_t *sol) {
  const ecu_tuning_t *tun = qp->tuning;
  OSQPSolver *const solver = qp->solver;
  const int n_pred = qp->n_pred, n_ctrl = qp->n_ctrl, n_soft_rows = qp->n_soft_rows;
  const int rows = 3 * n_pred, soft_first = n_ctrl + N_SOFT;
  double *const p_data = qp->p_data, *const a_data = qp->a_data, *const q = qp->q;
  double *const lower = qp->lower, *const upper = qp->upper, *const warm = qp->warm;
  const double *const pose_weight = qp->pose_weight, *const initial_dual = qp->initial_dual;
  const int *const soft_row = qp->soft_row;
  double weighted[3 * NP][NC];
  double hessian[NC][NC];
  use_weights(qp, vx);
  for (int r = 0; r < rows; r++)
    for (int c = 0; c < n_ctrl; c++) weighted[r][c] = jac[r * n_ctrl + c] * pose_weight[r];
  /* Half of OSQP's P: J' W J + the fixed part; its upper triangle in column order. */
  for (int a = 0; a < n_ctrl; a++) {
    for (int b = a; b < n_ctrl; b++) {
      double sum = 0.0;
      for (int r = 0; r < rows; r++) sum += jac[r * n_ctrl + a] * weighted[r][b];
      hessian[a][b] = sum + qp->fixed_hessian[a][b];
    }
  }
  int k = 0;
  for (int j = 0; j < n_ctrl; j++)
    for (int i = 0; i <= j; i++) p_data[k++] = 2.0 * hessian[i][j];
  for (int c = 0; c < n_ctrl; c++) {
    double sum = 0.0;
    for (int r = 0; r < rows; r++) sum += pose_offset[r] * weighted[r][c];
    q[c] = 2.0 * sum;
  }
  q[0] -= 2.0 * tun->p_steer_rate * previous_steer;
  /* The causal state-gain entries of A (both rows of a soft pair) and the soft bounds. */
  for (int j = 0; j < n_ctrl; j++) {
    double *col = a_data + qp->a_column[j] + 1;
    for (int r = qp->gain_first[j], k = 0; r < n_soft_rows; r++, k += 2)
      col[k] = col[k + 1] = gain[soft_row[r] * n_ctrl + j];
  }
  const int narrowed = yaw_rate_bound < INFINITY; /* the grip envelope's bound on the yaw-rate rows */
  for (int r = 0; r < n_soft_rows; r++) {
    const int row = soft_row[r], state = row % N_SOFT;
    double state_max = tun->state_max[state], state_min = tun->state_min[state];
    if (narrowed && state == YAW_RATE_STATE) { /* numpy.minimum / maximum of finite numbers */
      state_max = yaw_rate_bound < state_max ? yaw_rate_bound : state_max;
      state_min = -yaw_rate_bound > state_min ? -yaw_rate_bound : state_min;
    }
    upper[soft_first + 2 * r] = state_max - free_states[row];
    lower[soft_first + 2 * r + 1] = state_min - free_states[row];
  }
  if (qp->n_rate_rows > 0) { /* U_0 - U_{-1} within the step */
    lower[qp->rate_first] = previous_steer - qp->max_steer_step;
    upper[qp->rate_first] = previous_steer + qp->max_steer_step;
  }
  /* The Python interface's order: vectors first, then matrices (rescaled, refactored). */
  osqp_update_data_vec(solver, q, lower, upper);
  osqp_update_data_mat(solver, p_data, OSQP_NULL, n_ctrl * (n_ctrl + 1) / 2 + N_SOFT, a_data, OSQP_NULL, qp->a_count);
  for (int c = 0; c < n_ctrl; c++) warm[c] = warm_steer[c];
  /* Dual start at the inactive-constraint values unless a state constraint was active. */
  osqp_warm_start(solver, warm, qp->constraints_were_active ? OSQP_NULL : initial_dual);
  osqp_solve(solver);
  sol->status = map_status(solver->info->status_val);
  sol->iterations = (int)solver->info->iter;
  sol->solve_time_s = 0.0;
  const double *x = solver->solution->x, *y = solver->solution->y;
  for (int c = 0; c < n_ctrl; c++) sol->steer[c] = x[c];
  for (int s = 0; s < N_SOFT; s++) sol->slack[s] = x[n_ctrl + s];
  if (sol->status == ECU_SOLVED || sol->status == ECU_SOLVED_INACCURATE) {
    double largest = 0.0;
    for (int r = soft_first; r < soft_first + 2 * n_soft_rows; r++) largest = fmax(largest, fabs(y[r]));
    qp->constraints_were_active = largest > 1.0;
  } else {
    osqp_warm_start(solver, OSQP_NULL, initial_dual);
    qp->constraints_were_active = 0;
  }
  double constant = 0.0;
  for (int r = 0; r < rows; r++) constant += pose_offset[r] * (pose_offset[r] * pose_weight[r]);
  constant += tun->p_steer_rate * previous_steer * previous_steer;
  sol->cost = solver->info->obj_val + constant;
}

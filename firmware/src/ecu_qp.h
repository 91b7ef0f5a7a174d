/*
 * The steering QP of one core (ecu_qp.c), a port of controller/steering_qp.py on the
 * solvers OSQP generated at build time. OSQP's code generation writes each workspace as
 * static data, so the build generates ECU_QP_WORKSPACES of them per controller (ecu_build.h,
 * firmware/tools/generate.py); a core holds one of its controller's from ecu_qp_init to
 * ecu_qp_release, so that many cores of a controller can live in one process.
 */
#ifndef ECU_QP_H
#define ECU_QP_H

#include "ecu_config.h"
#include "osqp.h"

#define ECU_QP_N_SOFT 3
#define ECU_QP_N_VAR (ECU_NC_MAX + ECU_QP_N_SOFT)
/* ... + Nc steer-rate rows at most (qp_steer_rate_limit > 0) */
#define ECU_QP_N_CON (ECU_NC_MAX + ECU_QP_N_SOFT + 2 * ECU_QP_N_SOFT * ECU_NP_MAX + ECU_NC_MAX)
#define ECU_QP_P_NNZ (ECU_NC_MAX * (ECU_NC_MAX + 1) / 2 + ECU_QP_N_SOFT)
/* A's nonzeros at most (all causal) */
#define ECU_QP_A_NNZ (ECU_NC_MAX * (3 + 2 * ECU_QP_N_SOFT * ECU_NP_MAX) + ECU_QP_N_SOFT * (1 + 2 * ECU_NP_MAX))

typedef struct {
  OSQPSolver *solver;       /* the generated workspace held (NULL: none) */
  int controller, workspace;
  const ecu_tuning_t *tuning;
  int n_pred, n_ctrl;
  int constraints_were_active;
  double fixed_hessian[ECU_NC_MAX][ECU_NC_MAX], rate_diagonal[ECU_NC_MAX];
  double p_data[ECU_QP_P_NNZ], a_data[ECU_QP_A_NNZ], q[ECU_QP_N_VAR], lower[ECU_QP_N_CON], upper[ECU_QP_N_CON];
  double warm[ECU_QP_N_VAR], initial_dual[ECU_QP_N_CON], pose_weight[3 * ECU_NP_MAX];
  /* A's data: U column c starts at a_column[c] (its bound row; then the gain rows from
   * gain_first[c] on, both sides); the slack columns start at a_column[n_ctrl]. */
  int a_column[ECU_NC_MAX + 1], gain_first[ECU_NC_MAX], a_count;
  /* The soft rows: the r-th pair of rows bounds the flattened state soft_row[r] (3 step +
   * state, step-major as soft_state_rows); state k has soft_count[k] of them. */
  int soft_row[ECU_QP_N_SOFT * ECU_NP_MAX], n_soft_rows, soft_count[ECU_QP_N_SOFT];
  /* The steer-rate rows (SteeringQp's, after the soft rows): n_rate_rows (Nc, or 0 when
   * off) from row rate_first; max_steer_step = qp_steer_rate_limit * Ts (rad). */
  int rate_first, n_rate_rows;
  double max_steer_step;
} ecu_qp_t;

typedef struct {
  int status, iterations;
  double steer[ECU_NC_MAX], slack[3];
  double cost, solve_time_s;
} ecu_qp_solution_t;

/* Take a free generated workspace of `controller` (qp's own when it holds one of that
 * controller; another it holds is released) and apply the tuning's solver settings; tuning
 * must outlive qp. 0, or -1 with err (all ECU_QP_WORKSPACES in use, a refused setting). */
int ecu_qp_init(ecu_qp_t *qp, int controller, const ecu_tuning_t *tuning, char *err, size_t err_len);

/* Give the workspace back (nothing when none is held). */
void ecu_qp_release(ecu_qp_t *qp);

/* SteeringQp.solve: jac (Np*3 x Nc, row-major), offset (Np*3), gain (Np*3 x Nc, states at
 * steps 1..Np), free (Np*3), warm (Nc); vx (m/s) the measured speed the weights are
 * scheduled on; yaw_rate_bound (rad/s, > 0) the grip envelope's (ecu_grip.h), narrowing the
 * yaw-rate rows to within +-yaw_rate_bound for this solve (INFINITY: the table's bounds). */
void ecu_qp_solve(ecu_qp_t *qp, double vx, const double *jac, const double *pose_offset, double previous_steer,
                  const double *gain, const double *free_states, const double *warm, double yaw_rate_bound,
                  ecu_qp_solution_t *solution);

#endif

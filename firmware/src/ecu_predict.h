/*
 * The prediction of the steering MPCs over the horizon: the affine state prediction of
 * controller/lifted_mpc.py (Koopman, + the ESO's disturbance response of
 * controller/eso_dkmpc.py) and controller/lmpc.py (bicycle), and the pose linearisation
 * of controller/pose_kinematics.py. Pure functions but for the observer they advance.
 * Shapes: free (Np + 1, 3) and gain (Np + 1, 3, Nc) of the states [vx, vy, yaw_rate] at
 * steps 0..Np (gain: the held input map of the Nc steer moves).
 */
#ifndef ECU_PREDICT_H
#define ECU_PREDICT_H

#include "ecu_delay.h"
#include "ecu_observer.h"

/* What the forward step over the delay window needs of the last prediction, in the
 * controller's own model: Koopman z+ = A z + steer u + drift + disturbance (the step's
 * B(z_k) steer column, B's torque column times the torque plus the offset, the ESO's
 * w_hat or 0); bicycle [vy, yaw_rate]+ = transition x + b u at the step's speed. */
typedef struct {
  double drift[ECU_NZ], steer[ECU_NZ], disturbance[ECU_NZ];
  double transition[2][2], b[2], lateral[2];
} ecu_prediction_basis_t;

/* LiftedMpc.predict_states (+ EsoDkmpc.disturbance_response when observer is not NULL, with
 * decay_power[i] = disturbance_decay^i): lifts the sample into lifted (n_z,) and sets
 * model to the model at the measured speed, both kept for the observer's update. */
void ecu_predict_koopman(const ecu_config_t *cfg, const ecu_tuning_t *tuning, ecu_observer_t *observer,
                         const double *decay_power, const ecu_sample_t *sample, double torque,
                         ecu_local_model_t *model, double lifted[ECU_NZ], double free[][3],
                         double gain[][3][ECU_NC_MAX], ecu_prediction_basis_t *basis);

/* Lmpc.predict_states: the bicycle discretised at the measured speed (rounded), vx held. */
void ecu_predict_bicycle(const ecu_config_t *cfg, const ecu_tuning_t *tuning, const ecu_sample_t *sample,
                         double free[][3], double gain[][3][ECU_NC_MAX], ecu_prediction_basis_t *basis);

/* LiftedMpc.shift_start: the lifted state moved over the window by the step's model and
 * free (Np + 1, 3) moved by C_P A^i (z_d - z_k). */
void ecu_shift_koopman(const ecu_local_model_t *model, const ecu_prediction_basis_t *basis,
                       const double lifted[ECU_NZ], const ecu_delay_window_t *window, int n_pred, double free[][3]);

/* Lmpc.shift_start: [vy, yaw_rate] moved over the window, free's lateral rows by A^i (x_d - x_k). */
void ecu_shift_bicycle(const ecu_prediction_basis_t *basis, const ecu_delay_window_t *window, int n_pred,
                       double free[][3]);

/* linearise_pose (controller/pose_kinematics.py): nominal poses (Np, 3) at steps 1..Np and
 * the Jacobian (Np, 3, Nc) in U, from the nominal states (Np, 3) at steps 0..Np-1. */
void ecu_linearise_pose(double ts, const ecu_tuning_t *tuning, const ecu_sample_t *sample, double states[][3],
                        double gain[][3][ECU_NC_MAX], double poses[][3], double jac[][3][ECU_NC_MAX]);

#endif

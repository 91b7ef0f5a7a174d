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

#include "ecu_observer.h"

/* LiftedMpc.predict_states (+ EsoDkmpc.disturbance_response when observer is not NULL, with
 * decay_power[i] = disturbance_decay^i): lifts the sample into lifted (n_z,) and sets
 * model to the model at the measured speed, both kept for the observer's update. */
void ecu_predict_koopman(const ecu_config_t *cfg, const ecu_tuning_t *tuning, ecu_observer_t *observer,
                         const double *decay_power, const ecu_sample_t *sample, double torque,
                         ecu_local_model_t *model, double lifted[ECU_NZ], double free[][3],
                         double gain[][3][ECU_NC_MAX]);

/* Lmpc.predict_states: the bicycle discretised at the measured speed (rounded), vx held. */
void ecu_predict_bicycle(const ecu_config_t *cfg, const ecu_tuning_t *tuning, const ecu_sample_t *sample,
                         double free[][3], double gain[][3][ECU_NC_MAX]);

/* linearise_pose (controller/pose_kinematics.py): nominal poses (Np, 3) at steps 1..Np and
 * the Jacobian (Np, 3, Nc) in U, from the nominal states (Np, 3) at steps 0..Np-1. */
void ecu_linearise_pose(double ts, const ecu_tuning_t *tuning, const ecu_sample_t *sample, double states[][3],
                        double gain[][3][ECU_NC_MAX], double poses[][3], double jac[][3][ECU_NC_MAX]);

#endif

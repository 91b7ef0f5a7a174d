/*
 * One control task of the node every 25 ms (firmware_sim/control_task.py): events ->
 * mode transition -> request (the core's step, dead reckoning in DEGRADED, the safe stop,
 * the excitation) -> guard -> STEER_TORQUE_CMD and CTRL_DIAG -> timing record. Never fails:
 * a failing law becomes the guard's fallback command.
 */
#ifndef ECU_CONTROL_TASK_H
#define ECU_CONTROL_TASK_H

#include "ecu_node_state.h"

/* The task released at now_ns (virtual time in lockstep); release_jitter_s NaN in
 * lockstep; started_s the wall time the task's cycle began (CYCLE_TIME_US). */
void ecu_control_task(ecu_node_t *node, int64_t now_ns, double release_jitter_s, double started_s);

#endif

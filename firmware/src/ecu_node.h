/*
 * The ECU node: a port of firmware_sim/ecu.py (the cyclic executive) around the control
 * core (ecu_core.h), in lockstep with HIL_SYNC or on absolute 25 ms deadlines in real time.
 * Its parts are the inputs (ecu_rx_state.c, firmware_sim/rx.py), the control task
 * (ecu_control_task.c: events, modes, request, guard, TX), the transmitter (ecu_tx.c), the
 * mode logic (ecu_modes.c), dead reckoning (ecu_dead_reckoning.c) and the timing record
 * (ecu_timing.c). Pure logic: frames go out through the send function given to
 * ecu_node_start; no clock but os_monotonic_ns for the task's own time, no bus. All of a
 * node's state is one ecu_node_t, the caller's storage (static or zeroed; no heap).
 */
#ifndef ECU_NODE_H
#define ECU_NODE_H

#include <stddef.h>
#include <stdint.h>

#include "ecu_node_state.h"

/* The node on a loaded core, its paths and excitation: load_error NULL, or why the model or
 * a path failed (FAULT latched, as the Python ECU does). */
void ecu_node_start(ecu_node_t *node, ecu_core_t *core, const ecu_path_pool_t *paths, ecu_excite_t *excite,
                    ecu_send_fn send, const char *load_error);

/* One received frame (contract_kind: a classic data frame with an 11-bit ID); a HIL_SYNC
 * runs the due control tasks and answers. Never fails. */
void ecu_node_frame(ecu_node_t *node, uint32_t id, const uint8_t *data, int length, int contract_kind);

/* Real-time mode (instead of lockstep): arrivals stamped on the monotonic clock, HIL_SYNC
 * ignored, the control task released by ecu_node_poll on absolute 25 ms deadlines. */
void ecu_node_set_realtime(ecu_node_t *node);

/* Contract revision 3 (--release sample): the control task released by the arrival of a
 * good plant sample set in the window of each 25 ms instant, with the period watchdog
 * (ecu_release.h); in both time bases. Call after ecu_node_start. */
void ecu_node_set_sample_release(ecu_node_t *node);

/* Revision 3 (--plant-period 25): the plant's sample period, for the continuity check of
 * a sample (10 ms in revision 2). Call after ecu_node_start. */
void ecu_node_set_plant_period(ecu_node_t *node, int period_ms);

/* Real time: run the control task if its release has come; returns the next release (ns
 * on os_monotonic_ns; revision 3: the latest the next release can come, its watchdog). */
int64_t ecu_node_poll(ecu_node_t *node, int64_t now_ns);

/* On stopping: one last STEER_TORQUE_CMD with CMD_VALID = 0 (STANDBY, FAULT when latched),
 * the held steering angle and zero torque. */
void ecu_node_close(ecu_node_t *node);

#endif

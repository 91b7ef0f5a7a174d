/*
 * The ECU node in lockstep: a port of firmware_sim/ecu.py (the cyclic executive),
 * firmware_sim/rx.py (sample assembly, plausibility), firmware_sim/modes.py,
 * firmware_sim/guard.py, firmware_sim/safe_stop.py, firmware_sim/tx.py and
 * controller/dead_reckoning.py around the control core (ecu_core.c). Pure logic: frames
 * go out through the send function given to ecu_node_init; no clock, no bus.
 */
#ifndef ECU_NODE_H
#define ECU_NODE_H

#include <stddef.h>
#include <stdint.h>

#include "ecu_core.h"

typedef int (*ecu_send_fn)(uint32_t id, const uint8_t *data, int length);

/* The node on a loaded core: load_error NULL, or why the model or a path failed (FAULT
 * latched, as the Python ECU does). */
ECU_API void ecu_node_init(ecu_send_fn send, const char *load_error);

/* One received frame (contract_kind: a classic data frame with an 11-bit ID); a HIL_SYNC
 * runs the due control tasks and answers. Never fails. */
ECU_API void ecu_node_receive(uint32_t id, const uint8_t *data, int length, int contract_kind);

/* Real-time mode (instead of lockstep): arrivals stamped on the monotonic clock, HIL_SYNC
 * ignored, the control task released by ecu_node_poll on absolute 25 ms deadlines. */
ECU_API void ecu_node_set_realtime(void);

/* Real time: run the control task if its release has come; returns the next release (ns
 * on os_monotonic_ns). */
ECU_API int64_t ecu_node_poll(int64_t now_ns);

/* On stopping: one last STEER_TORQUE_CMD with CMD_VALID = 0 (STANDBY, FAULT when latched),
 * the held steering angle and zero torque. */
ECU_API void ecu_node_close(void);

/* Write the timing record (the last 65,536 control tasks) as firmware_sim.timing's .npz
 * (``--timing-out``); 0, or -1 with err. */
ECU_API int ecu_node_save_timing(const char *path, char *err, size_t err_len);

/* The node's mode (CTRL_MODE values) and its counts, for logs and tests. */
ECU_API int ecu_node_mode(void);
ECU_API int ecu_node_cycles(void);

#endif

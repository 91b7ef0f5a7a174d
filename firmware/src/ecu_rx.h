/*
 * The receive side of the bus contract in C: the E2E check (CRC-8 SAE J1850, alive
 * counters; a port of can_defs/e2e.py and can_defs/crc.py) and the decoding of the
 * frames the ECU receives, on cantools' generated codecs (build/firmware/gen/can).
 */
#ifndef ECU_RX_H
#define ECU_RX_H

#include <stdint.h>

#include "ecu_types.h"

/* can_defs.e2e.E2EStatus, in the order of its members. */
enum ecu_e2e_status {
  ECU_E2E_OK = 0, ECU_E2E_CRC_ERROR = 1, ECU_E2E_REPEATED = 2, ECU_E2E_LOST = 3,
  ECU_E2E_SEQUENCE_ERROR = 4, ECU_E2E_WRONG_LENGTH = 5, ECU_E2E_UNKNOWN_ID = 6, ECU_E2E_BAD_TICK = 7
};

/* One verdict: status, frames counted as lost before this one, whether it may be used. */
typedef struct {
  int status, lost, accepted;
} ecu_e2e_result_t;

/* The contract's frames (one receiver each). */
#define ECU_E2E_FRAMES 8

/* E2EMonitor: per frame, whether a counter reference is held and the last counter. A
 * zeroed monitor is a reset one. */
typedef struct {
  int synchronised[ECU_E2E_FRAMES], last_counter[ECU_E2E_FRAMES];
} ecu_e2e_monitor_t;

/* CRC of an E2E-protected frame: over the identifier (low, high byte) and bytes 1..7. */
ECU_API uint8_t ecu_e2e_crc(uint32_t frame_id, const uint8_t data[8]);

/* E2EMonitor.check: classify one received frame (any length, any ID); never fails. */
ecu_e2e_result_t ecu_e2e_monitor_check(ecu_e2e_monitor_t *monitor, uint32_t frame_id, const uint8_t *data,
                                       int length);

/* E2EMonitor.reset: forget every counter reference. */
void ecu_e2e_monitor_reset(ecu_e2e_monitor_t *monitor);

/* The physical values of a received contract frame (8 bytes), in the order of
 * can_defs.frames' dataclass fields: VEH_DYN vx, vy, yaw_rate; VEH_POSE_XY x, y;
 * VEH_POSE_YAW yaw, steer_angle, drive_torque; PLANNER_REQ engage, target_speed, path_id;
 * HIL_SYNC / HIL_SYNC_ACK tick. Returns the number of values, or -1 for another ID. */
ECU_API int ecu_decode(uint32_t frame_id, const uint8_t data[8], double values[3]);

#endif

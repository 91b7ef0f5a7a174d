/*
 * E2E receive (can_defs/e2e.py) and frame decoding (cantools' generated codecs).
 * One receiver per contract frame ID in the caller's ecu_e2e_monitor_t; the CRC table is
 * the only static (a constant, computed on first use).
 */
#include <string.h>

#include "ecu_rx.h"
#include "vehicle.h"

#define FRAME_LENGTH 8
#define COUNTER_MODULUS 16
#define MAX_TOLERATED_LOST 2 /* a counter jump of 2 or 3 is still accepted */
#define TICK_STEP_MS 5u
#define HANDSHAKE_TICK 0xFFFFFFFFu
#define CRC_POLY 0x1Du
#define CRC_INIT 0xFFu
#define CRC_XOR_OUT 0xFFu

/* The contract's frame IDs; the first two (HIL frames) carry no CRC or counter. */
static const uint32_t FRAME_IDS[] = {
  VEHICLE_HIL_SYNC_FRAME_ID, VEHICLE_HIL_SYNC_ACK_FRAME_ID, VEHICLE_VEH_DYN_FRAME_ID,
  VEHICLE_VEH_POSE_XY_FRAME_ID, VEHICLE_VEH_POSE_YAW_FRAME_ID, VEHICLE_PLANNER_REQ_FRAME_ID,
  VEHICLE_STEER_TORQUE_CMD_FRAME_ID, VEHICLE_CTRL_DIAG_FRAME_ID};
#define N_FRAMES ((int)(sizeof FRAME_IDS / sizeof FRAME_IDS[0]))
#define N_HIL_FRAMES 2
_Static_assert(N_FRAMES == ECU_E2E_FRAMES, "ecu_rx.h: ECU_E2E_FRAMES is the number of contract frames");

static int initialised;
static uint8_t crc_table[256];

static void initialise(void) {
  /* CRC of every byte value with a zero register: one look-up per byte. */
  for (int byte = 0; byte < 256; byte++) {
    uint8_t reg = (uint8_t)byte;
    for (int bit = 0; bit < 8; bit++) reg = (uint8_t)((reg & 0x80u) ? ((unsigned)reg << 1) ^ CRC_POLY : (unsigned)reg << 1);
    crc_table[byte] = reg;
  }
  initialised = 1;
}

uint8_t ecu_e2e_crc(uint32_t frame_id, const uint8_t data[8]) {
  if (!initialised) initialise();
  uint8_t reg = CRC_INIT;
  reg = crc_table[reg ^ (frame_id & 0xFFu)];
  reg = crc_table[reg ^ ((frame_id >> 8) & 0xFFu)];
  for (int i = 1; i < FRAME_LENGTH; i++) reg = crc_table[reg ^ data[i]];
  return (uint8_t)(reg ^ CRC_XOR_OUT);
}

void ecu_e2e_monitor_reset(ecu_e2e_monitor_t *monitor) { memset(monitor, 0, sizeof *monitor); }

static ecu_e2e_result_t verdict(int status, int lost, int accepted) {
  ecu_e2e_result_t result = {status, lost, accepted};
  return result;
}

ecu_e2e_result_t ecu_e2e_monitor_check(ecu_e2e_monitor_t *monitor, uint32_t frame_id, const uint8_t *data,
                                       int length) {
  int slot = -1;
  if (!initialised) initialise();
  for (int i = 0; i < N_FRAMES; i++)
    if (FRAME_IDS[i] == frame_id) slot = i;
  if (slot < 0) return verdict(ECU_E2E_UNKNOWN_ID, 0, 0);
  if (data == NULL || length != FRAME_LENGTH) return verdict(ECU_E2E_WRONG_LENGTH, 0, 0);
  if (slot < N_HIL_FRAMES) {
    uint32_t tick = (uint32_t)data[0] | (uint32_t)data[1] << 8 | (uint32_t)data[2] << 16 | (uint32_t)data[3] << 24;
    return tick % TICK_STEP_MS == 0 || tick == HANDSHAKE_TICK ? verdict(ECU_E2E_OK, 0, 1)
                                                              : verdict(ECU_E2E_BAD_TICK, 0, 0);
  }
  if (data[0] != ecu_e2e_crc(frame_id, data)) return verdict(ECU_E2E_CRC_ERROR, 0, 0);
  int counter = data[1] & 0x0F, last = monitor->last_counter[slot];
  if (!monitor->synchronised[slot]) {
    monitor->synchronised[slot] = 1;
    monitor->last_counter[slot] = counter;
    return verdict(ECU_E2E_OK, 0, 1);
  }
  int jump = (counter - last + COUNTER_MODULUS) % COUNTER_MODULUS;
  if (jump == 1) {
    monitor->last_counter[slot] = counter;
    return verdict(ECU_E2E_OK, 0, 1);
  }
  if (jump == 0) return verdict(ECU_E2E_REPEATED, 0, 0);
  if (jump <= MAX_TOLERATED_LOST + 1) {
    monitor->last_counter[slot] = counter;
    return verdict(ECU_E2E_LOST, jump - 1, 1);
  }
  /* Too many frames missing to trust the sequence: the next good frame re-synchronises. */
  monitor->synchronised[slot] = 0;
  return verdict(ECU_E2E_SEQUENCE_ERROR, jump - 1, 0);
}

int ecu_decode(uint32_t frame_id, const uint8_t data[8], double values[3]) {
  switch (frame_id) {
    case VEHICLE_VEH_DYN_FRAME_ID: {
      struct vehicle_veh_dyn_t m;
      vehicle_veh_dyn_unpack(&m, data, FRAME_LENGTH);
      values[0] = vehicle_veh_dyn_vx_decode(m.vx);
      values[1] = vehicle_veh_dyn_vy_decode(m.vy);
      values[2] = vehicle_veh_dyn_yaw_rate_decode(m.yaw_rate);
      return 3;
    }
    case VEHICLE_VEH_POSE_XY_FRAME_ID: {
      struct vehicle_veh_pose_xy_t m;
      vehicle_veh_pose_xy_unpack(&m, data, FRAME_LENGTH);
      values[0] = vehicle_veh_pose_xy_pos_x_decode(m.pos_x);
      values[1] = vehicle_veh_pose_xy_pos_y_decode(m.pos_y);
      return 2;
    }
    case VEHICLE_VEH_POSE_YAW_FRAME_ID: {
      struct vehicle_veh_pose_yaw_t m;
      vehicle_veh_pose_yaw_unpack(&m, data, FRAME_LENGTH);
      values[0] = vehicle_veh_pose_yaw_yaw_decode(m.yaw);
      values[1] = vehicle_veh_pose_yaw_steer_angle_decode(m.steer_angle);
      values[2] = vehicle_veh_pose_yaw_drive_torque_decode(m.drive_torque);
      return 3;
    }
    case VEHICLE_PLANNER_REQ_FRAME_ID: {
      struct vehicle_planner_req_t m;
      vehicle_planner_req_unpack(&m, data, FRAME_LENGTH);
      values[0] = vehicle_planner_req_engage_decode(m.engage);
      values[1] = vehicle_planner_req_target_speed_decode(m.target_speed);
      values[2] = vehicle_planner_req_path_id_decode(m.path_id);
      return 3;
    }
    case VEHICLE_HIL_SYNC_FRAME_ID: {
      struct vehicle_hil_sync_t m;
      vehicle_hil_sync_unpack(&m, data, FRAME_LENGTH);
      values[0] = vehicle_hil_sync_tick_decode(m.tick);
      return 1;
    }
    case VEHICLE_HIL_SYNC_ACK_FRAME_ID: {
      struct vehicle_hil_sync_ack_t m;
      vehicle_hil_sync_ack_unpack(&m, data, FRAME_LENGTH);
      values[0] = vehicle_hil_sync_ack_tick_decode(m.tick);
      return 1;
    }
    default:
      return -1;
  }
}

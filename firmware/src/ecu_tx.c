/*
 * The node's transmitter (see ecu_tx.h).
 */
#include <math.h>
#include <string.h>

#include "ecu_rx.h"
#include "ecu_tx.h"
#include "vehicle.h"

static double clamp(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

static void send_e2e(ecu_tx_t *tx, uint32_t id, int slot, uint8_t data[8]) {
  data[1] = (uint8_t)((data[1] & 0xF0u) | (unsigned)tx->counter[slot]);
  tx->counter[slot] = (tx->counter[slot] + 1) % 16;
  data[0] = ecu_e2e_crc(id, data);
  tx->send(id, data, 8);
}

/* Physical -> raw as cantools' Python encoder: (value - offset) / scale, rounded half to even. */
static long raw_of(double value, double scale, double lo, double hi) {
  return (long)nearbyint(clamp(value, lo, hi) / scale);
}

void ecu_tx_command(ecu_tx_t *tx, int mode, int cmd_valid, double steer, double torque) {
  struct vehicle_steer_torque_cmd_t m;
  uint8_t data[8];
  memset(&m, 0, sizeof m);
  m.ctrl_mode = (uint8_t)mode;
  m.cmd_valid = (uint8_t)cmd_valid;
  m.steer_angle_cmd = (int16_t)raw_of(steer, 0.0001, -3.2768, 3.2767);
  m.drive_torque_cmd = (int16_t)raw_of(torque, 0.1, -3276.8, 3276.7);
  vehicle_steer_torque_cmd_pack(data, &m, sizeof data);
  send_e2e(tx, VEHICLE_STEER_TORQUE_CMD_FRAME_ID, 0, data);
}

/* tx.saturate_int: round and clamp to 0..upper (non-finite -> upper). */
static unsigned saturate(double value, unsigned upper) {
  if (!(value == value) || value == INFINITY) return upper;
  double r = nearbyint(value);
  return r < 0.0 ? 0u : (r > (double)upper ? upper : (unsigned)r);
}

void ecu_tx_diag(ecu_tx_t *tx, int qp_status, double solve_time_s, double cycle_time_s, int iterations, int overruns,
                 int faults) {
  struct vehicle_ctrl_diag_t m;
  uint8_t data[8];
  memset(&m, 0, sizeof m);
  m.qp_status = (uint8_t)qp_status;
  m.solve_time_us = (uint16_t)saturate(solve_time_s * 1e6, 0xFFFF);
  m.cycle_time_us = (uint16_t)saturate(cycle_time_s * 1e6, 0xFFFF);
  m.qp_iter = (uint8_t)saturate(iterations, 0xFF);
  m.overruns = (uint8_t)saturate(overruns < 15 ? overruns : 15, 15);
  m.faults = (uint8_t)(faults & 0xF);
  vehicle_ctrl_diag_pack(data, &m, sizeof data);
  send_e2e(tx, VEHICLE_CTRL_DIAG_FRAME_ID, 1, data);
}

void ecu_tx_ack(ecu_tx_t *tx, uint32_t tick) {
  struct vehicle_hil_sync_ack_t m = {tick};
  uint8_t data[8];
  vehicle_hil_sync_ack_pack(data, &m, sizeof data);
  tx->send(VEHICLE_HIL_SYNC_ACK_FRAME_ID, data, 8);
}

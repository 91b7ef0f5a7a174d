/*
 * The node's transmitter (firmware_sim/tx.py): STEER_TORQUE_CMD and CTRL_DIAG with their
 * E2E protection (CRC, alive counter), HIL_SYNC_ACK; through cantools' generated codecs.
 */
#ifndef ECU_TX_H
#define ECU_TX_H

#include <stdint.h>

typedef int (*ecu_send_fn)(uint32_t id, const uint8_t *data, int length);

typedef struct {
  ecu_send_fn send;
  int counter[2]; /* alive counters: STEER_TORQUE_CMD, CTRL_DIAG */
} ecu_tx_t;

/* STEER_TORQUE_CMD (physical values; CTRL_MODE mode). */
void ecu_tx_command(ecu_tx_t *tx, int mode, int cmd_valid, double steer, double torque);

/* CTRL_DIAG (times in s; every field saturated to its range). */
void ecu_tx_diag(ecu_tx_t *tx, int qp_status, double solve_time_s, double cycle_time_s, int iterations, int overruns,
                 int faults);

/* HIL_SYNC_ACK of TICK tick. */
void ecu_tx_ack(ecu_tx_t *tx, uint32_t tick);

#endif

/*
 * The state of one ECU node (ecu_node.h): what it runs on, its inputs, transmitter, modes
 * and timing record, all in one ecu_node_t that the caller owns (static or zeroed; no
 * heap). Apart from the node's functions so that its parts (the control task) take the
 * node without including the node's interface.
 */
#ifndef ECU_NODE_STATE_H
#define ECU_NODE_STATE_H

#include <stdint.h>

#include "ecu_core.h"
#include "ecu_excite.h"
#include "ecu_release.h"
#include "ecu_rx_state.h"
#include "ecu_timing.h"
#include "ecu_tx.h"

typedef struct {
  /* What the node runs on (the caller's, loaded at start-up). */
  ecu_core_t *core;
  const ecu_path_pool_t *paths;
  ecu_excite_t *excite;
  const char *load_error; /* NULL, or why the model or a path failed (FAULT latched) */
  ecu_tx_t tx;
  ecu_rx_state_t rx;
  /* Ecu */
  int mode, awaiting_disengage, active_path_id, pending_model_reset, overruns, cycles;
  int fallback_streak; /* control tasks in a row whose command was the fallback in ACTIVE / DEGRADED */
  double previous_valid_steer;
  int synchronised;
  ecu_when_t last_tick;
  int realtime, warned_sync, release_started;
  int64_t next_release;
  int sample_release;    /* revision 3: the control task released by the plant's samples */
  ecu_release_t release; /* its grid of control instants (ecu_release.h) */
  int plant_period_ms;   /* the plant's sample period (0: 10 ms; revision 3 allows 25) */
  ecu_output_t out; /* the core's output of the task running (no state between tasks) */
  ecu_timing_t timing;
} ecu_node_t;

#endif

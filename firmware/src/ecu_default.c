/*
 * The default instances (see ecu_default.h): static storage, so nothing is allocated.
 */
#include "ecu_default.h"

static ecu_core_t core;
static ecu_path_pool_t paths;
static ecu_e2e_monitor_t monitor;
static ecu_excite_t no_excitation; /* zeroed: disabled */
static ecu_node_t node;

int ecu_load(const char *data_path, const char *controller, char *err, size_t err_len) {
  return ecu_core_load(&core, data_path, controller, err, err_len);
}

int ecu_set_path(const double *x, const double *y, const double *yaw, const double *s, int n, char *err,
                 size_t err_len) {
  return ecu_core_set_path(&core, x, y, yaw, s, n, err, err_len);
}

int ecu_path_copy(double *x, double *y, double *yaw, double *s, int max) {
  return ecu_core_path_copy(&core, x, y, yaw, s, max);
}

void ecu_reset(void) { ecu_core_reset(&core); }

void ecu_step(const ecu_sample_t *sample, ecu_output_t *out) { ecu_core_step(&core, sample, out); }

void ecu_step_aged(const ecu_sample_t *sample, double sample_age_s, ecu_output_t *out) {
  ecu_core_step_aged(&core, sample, sample_age_s, out);
}

double ecu_yaw_rate_bound(void) { return core.yaw_rate_bound; }

int ecu_load_path_csv(const char *file, char *err, size_t err_len) {
  ecu_paths_reset(&paths);
  if (ecu_paths_add(&paths, 0, file, err, err_len) != 0) return -1;
  return ecu_core_select_path(&core, &paths, 0, err, err_len);
}

ecu_e2e_result_t ecu_e2e_check(uint32_t frame_id, const uint8_t *data, int length) {
  return ecu_e2e_monitor_check(&monitor, frame_id, data, length);
}

void ecu_e2e_reset(void) { ecu_e2e_monitor_reset(&monitor); }

void ecu_node_init(ecu_send_fn send, const char *load_error) {
  ecu_node_start(&node, &core, &paths, &no_excitation, send, load_error);
}

void ecu_node_receive(uint32_t id, const uint8_t *data, int length, int contract_kind) {
  ecu_node_frame(&node, id, data, length, contract_kind);
}

int ecu_node_mode(void) { return node.mode; }

int ecu_node_save_timing(const char *path, char *err, size_t err_len) {
  return ecu_timing_save(&node.timing, path, err, err_len);
}

/*
 * The process's default instances and the functions on them that libecu.so exports for
 * the Python twin (firmware_sim/native.py, ctypes): one core, its path pool, one E2E
 * monitor, one node (on the default core and pool, without excitation). C callers and
 * tests that want several build their own ecu_core_t / ecu_node_t instead.
 */
#ifndef ECU_DEFAULT_H
#define ECU_DEFAULT_H

#include <stddef.h>
#include <stdint.h>

#include "ecu_node.h"

/* ecu_core_load / set_path / path_copy / reset / step on the default core. */
ECU_API int ecu_load(const char *data_path, const char *controller, char *err, size_t err_len);
ECU_API int ecu_set_path(const double *x, const double *y, const double *yaw, const double *s, int n, char *err,
                         size_t err_len);
ECU_API int ecu_path_copy(double *x, double *y, double *yaw, double *s, int max);
ECU_API void ecu_reset(void);
ECU_API void ecu_step(const ecu_sample_t *sample, ecu_output_t *out);
/* ecu_core_step_aged on the default core: the sample's age at the task start (s). */
ECU_API void ecu_step_aged(const ecu_sample_t *sample, double sample_age_s, ecu_output_t *out);
/* The grip envelope's yaw-rate bound of the default core's last plan (rad/s; INFINITY: none,
 * the table's bounds), QpSteeringMpc._yaw_rate_bound: for the twin tests. */
ECU_API double ecu_yaw_rate_bound(void);

/* Read and check a path CSV as controller.reference.ReferencePath.from_csv does (the
 * contract's checks, the same messages) into the default pool as PATH_ID 0 (the pool's
 * other paths are forgotten), then make it the default core's path. 0 or -1 + err. */
ECU_API int ecu_load_path_csv(const char *file, char *err, size_t err_len);

/* ecu_e2e_monitor_check / reset on the default monitor. */
ECU_API ecu_e2e_result_t ecu_e2e_check(uint32_t frame_id, const uint8_t *data, int length);
ECU_API void ecu_e2e_reset(void);

/* ecu_node_start / frame on the default node; its mode (CTRL_MODE) and timing record. */
ECU_API void ecu_node_init(ecu_send_fn send, const char *load_error);
ECU_API void ecu_node_receive(uint32_t id, const uint8_t *data, int length, int contract_kind);
ECU_API int ecu_node_mode(void);
ECU_API int ecu_node_save_timing(const char *path, char *err, size_t err_len);

#endif

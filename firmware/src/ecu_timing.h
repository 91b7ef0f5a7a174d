/*
 * The timing record (firmware_sim.timing.TimingRecorder): the last ECU_TIMING_CAPACITY
 * control tasks, fields TIMING_FIELDS (s; overruns a count) and the context start_time,
 * mode; written as its .npz (``--timing-out``).
 */
#ifndef ECU_TIMING_H
#define ECU_TIMING_H

#include <stddef.h>
#include <stdint.h>

#define ECU_TIMING_CAPACITY 65536
#define ECU_TIMING_FIELDS 6

typedef struct {
  double rows[ECU_TIMING_CAPACITY][ECU_TIMING_FIELDS];
  double context[ECU_TIMING_CAPACITY][2];
  int64_t count; /* control tasks recorded since the run started */
} ecu_timing_t;

/* One task: release jitter, task time, solve time, input age, RX-to-TX latency (s), the
 * overruns so far; its release time (ns) and mode. */
void ecu_timing_record(ecu_timing_t *timing, const double row[ECU_TIMING_FIELDS], int64_t now_ns, int mode);

/* Write the record (oldest first) as the .npz of firmware_sim.timing; 0, or -1 with err.
 * Once, at exit: the ring is rotated in place. */
int ecu_timing_save(ecu_timing_t *timing, const char *path, char *err, size_t err_len);

#endif

/*
 * The timing record (see ecu_timing.h).
 */
#include <stdio.h>
#include <string.h>

#include "ecu_npz.h"
#include "ecu_timing.h"

void ecu_timing_record(ecu_timing_t *timing, const double row[ECU_TIMING_FIELDS], int64_t now_ns, int mode) {
  int64_t i = timing->count % ECU_TIMING_CAPACITY;
  memcpy(timing->rows[i], row, sizeof timing->rows[i]);
  timing->context[i][0] = (double)now_ns / 1e9;
  timing->context[i][1] = mode;
  timing->count++;
}

/* Reverse the rows lo..hi-1 of a ring (row_len doubles each), in place. */
static void reverse_rows(double *base, int row_len, int64_t lo, int64_t hi) {
  double tmp[ECU_TIMING_FIELDS];
  for (hi--; lo < hi; lo++, hi--) {
    memcpy(tmp, base + lo * row_len, (size_t)row_len * sizeof(double));
    memcpy(base + lo * row_len, base + hi * row_len, (size_t)row_len * sizeof(double));
    memcpy(base + hi * row_len, tmp, (size_t)row_len * sizeof(double));
  }
}

int ecu_timing_save(ecu_timing_t *timing, const char *path, char *err, size_t err_len) {
  static const char fields[ECU_TIMING_FIELDS][16] = {"release_jitter", "task_time", "solve_time", "input_age",
                                                   "rx_to_tx_latency", "overruns"};
  static const char context_fields[2][10] = {"start_time", "mode"};
  static uint32_t field_text[ECU_TIMING_FIELDS][16], context_text[2][10]; /* numpy '<U': UTF-32 */
  int64_t n = timing->count < ECU_TIMING_CAPACITY ? timing->count : ECU_TIMING_CAPACITY;
  int64_t first = timing->count < ECU_TIMING_CAPACITY ? 0 : timing->count % ECU_TIMING_CAPACITY;
  /* Oldest first, as TimingRecorder.rows(): rotate the full ring in place (three
   * reversals), so no second buffer is needed; the record is written once, at exit. */
  if (first) {
    reverse_rows(&timing->rows[0][0], ECU_TIMING_FIELDS, 0, first);
    reverse_rows(&timing->rows[0][0], ECU_TIMING_FIELDS, first, n);
    reverse_rows(&timing->rows[0][0], ECU_TIMING_FIELDS, 0, n);
    reverse_rows(&timing->context[0][0], 2, 0, first);
    reverse_rows(&timing->context[0][0], 2, first, n);
    reverse_rows(&timing->context[0][0], 2, 0, n);
  }
  for (int f = 0; f < ECU_TIMING_FIELDS; f++)
    for (int c = 0; c < 16; c++) field_text[f][c] = (uint8_t)fields[f][c];
  for (int f = 0; f < 2; f++)
    for (int c = 0; c < 10; c++) context_text[f][c] = (uint8_t)context_fields[f][c];
  char rows_shape[40], context_shape[40];
  snprintf(rows_shape, sizeof rows_shape, "(%lld, %d)", (long long)n, ECU_TIMING_FIELDS);
  snprintf(context_shape, sizeof context_shape, "(%lld, 2)", (long long)n);
  int64_t count = timing->count;
  const npz_array_t arrays[] = {
    {"rows", "<f8", rows_shape, timing->rows, (size_t)n * sizeof timing->rows[0]},
    {"context", "<f8", context_shape, timing->context, (size_t)n * sizeof timing->context[0]},
    {"fields", "<U16", "(6,)", field_text, sizeof field_text},
    {"context_fields", "<U10", "(2,)", context_text, sizeof context_text},
    {"count", "<i8", "()", &count, sizeof count},
  };
  return npz_write(path, arrays, 5, err, err_len);
}

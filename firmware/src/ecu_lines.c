/* Bounded line reading (ecu_lines.h); a port of models/input_files.py's bounded_lines. */
#include <string.h>

#include "ecu_lines.h"

int ecu_read_line(ecu_lines_t *lines, char *buf, char *err, size_t err_len) {
  size_t n = 0;
  int c = 0;
  while (n < ECU_LINE_MAX + 1 && (c = getc(lines->stream)) != EOF) {
    buf[n++] = (char)c;
    if (c == '\n') break;
  }
  if (n == 0) return 0;
  lines->number++;
  lines->total_bytes += (long)n;
  if (memchr(buf, '\0', n)) {
    snprintf(err, err_len, "%s: line %d: holds a NUL byte", lines->name, lines->number);
    return -1;
  }
  if (n > ECU_LINE_MAX) {
    snprintf(err, err_len, "%s: line %d: longer than %d bytes", lines->name, lines->number, ECU_LINE_MAX);
    return -1;
  }
  if (lines->total_bytes > lines->max_bytes) {
    snprintf(err, err_len, "%s: larger than %ld bytes (the limit of this file)", lines->name, lines->max_bytes);
    return -1;
  }
  if (buf[n - 1] == '\n') n--; /* the line's end: "\n" or "\r\n" */
  if (n > 0 && buf[n - 1] == '\r') n--;
  buf[n] = '\0';
  return 1;
}

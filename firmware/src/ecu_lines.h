/*
 * Bounded line reading of the ECU's text input files (path CSVs, excitation programs),
 * the same rules as the Python ECU's models/input_files.py, so that both ECUs give the same
 * verdict on the same file: a line is at most ECU_LINE_MAX bytes with its end, holds no NUL
 * byte and is UTF-8, and a file is at most its own limit of bytes in all. Memory stays
 * bounded on any input (a pipe, /dev/zero): reading stops at the first line that breaks a
 * rule.
 */
#ifndef ECU_LINES_H
#define ECU_LINES_H

#include <stddef.h>
#include <stdio.h>

/* Bytes of one line with its end ("\n", "\r\n"); a buffer holds ECU_LINE_MAX + 2. */
#define ECU_LINE_MAX 4096
/* Bytes of a path file (100,000 points of up to 160 bytes) and of an excitation program. */
#define ECU_PATH_FILE_MAX 16777216L
#define ECU_EXCITE_FILE_MAX 4194304L

/* A text file being read: its name (for messages), stream, size limit and position. */
typedef struct {
  const char *name;
  FILE *stream;
  long max_bytes;
  long total_bytes;
  int number; /* 1-based number of the line last read */
} ecu_lines_t;

/* The next line into buf (ECU_LINE_MAX + 2 bytes), its "\r\n" / "\n" end removed.
 * 1: a line; 0: the end of the file; -1: err holds "FILE: line N: holds a NUL byte",
 * "FILE: line N: longer than 4096 bytes", "FILE: larger than M bytes (the limit of this
 * file)" or "FILE: line N: not UTF-8" (checked in that order, as bounded_lines). */
int ecu_read_line(ecu_lines_t *lines, char *buf, char *err, size_t err_len);

#endif

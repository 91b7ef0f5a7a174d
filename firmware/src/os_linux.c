/*
 * The OS layer on Linux (POSIX clocks and signals). The only file with OS calls; the
 * rest of the firmware is C11 with libc's stdio and libm.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <signal.h>
#include <string.h>
#include <time.h>

#include "os.h"

int64_t os_monotonic_ns(void) {
  struct timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  return (int64_t)now.tv_sec * 1000000000 + now.tv_nsec;
}

int os_sleep_until_ns(int64_t deadline_ns) {
  struct timespec deadline = {(time_t)(deadline_ns / 1000000000), (long)(deadline_ns % 1000000000)};
  int status = clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &deadline, NULL);
  return status == 0 ? 0 : -1;
}

static volatile sig_atomic_t *stop_flag;

static void on_stop_signal(int signum) {
  (void)signum;
  if (stop_flag) *stop_flag = 1;
}

void os_install_stop_handler(volatile sig_atomic_t *stop) {
  struct sigaction action;
  memset(&action, 0, sizeof action);
  action.sa_handler = on_stop_signal;
  sigemptyset(&action.sa_mask);
  stop_flag = stop;
  sigaction(SIGINT, &action, NULL);
  sigaction(SIGTERM, &action, NULL);
  sigaction(SIGHUP, &action, NULL);
}

/*
 * The operating-system layer: everything the firmware needs from the OS, implemented in
 * one file per OS (os_linux.c). Porting to an RTOS or bare metal replaces that file only.
 */
#ifndef ECU_OS_H
#define ECU_OS_H

#include <signal.h>
#include <stdint.h>

/* Monotonic time in ns (never jumps with the wall clock). */
int64_t os_monotonic_ns(void);

/* Sleep until the monotonic time deadline_ns (absolute, so periods do not drift);
 * returns at once when it has passed. 0, or -1 when interrupted by a signal. */
int os_sleep_until_ns(int64_t deadline_ns);

/* SIGINT, SIGTERM and SIGHUP set *stop to 1 (the loops poll it). */
void os_install_stop_handler(volatile sig_atomic_t *stop);

#endif

/*
 * Delay compensation's window (ecu_delay.c): a port of controller/delay_compensation.py.
 * The delay from a sample to its command's effect (the tuning's delay_compensation_s plus
 * the sample's age) as whole model steps plus a fraction of one, the commands in flight
 * over it, and the pose at its end.
 */
#ifndef ECU_DELAY_H
#define ECU_DELAY_H

/* Commands kept for the window (controller.delay_compensation.COMMAND_HISTORY). */
#define ECU_COMMAND_HISTORY 8

typedef struct {
  int whole_steps;
  double fraction;
  double inputs[ECU_COMMAND_HISTORY]; /* the command in flight per grid step 0..whole_steps */
} ecu_delay_window_t;

/* total_delay: fixed + age (s); 0 when fixed is 0 (off); an age not finite or < 0 counts 0. */
double ecu_total_delay(double fixed_s, double age_s);

/* delay_window: history[0..n-1] the commands sent, oldest first (n >= 1). */
void ecu_delay_window(double delay_s, double ts, const double *history, int n, ecu_delay_window_t *window);

/* pose_after: pose0 (3,) moved with states (whole_steps + 1, 3) into pose, each step along its
 * yaw plus heading_advance of its own turn (0: explicit Euler, eq. 20; 0.5: the midpoint). */
void ecu_pose_after(const double pose0[3], const double states[][3], double ts, const ecu_delay_window_t *window,
                    double heading_advance, double pose[3]);

#endif

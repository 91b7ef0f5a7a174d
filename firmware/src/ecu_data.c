/*
 * The data file's reader (layout: firmware/tools/ecu_data.py). Every record is checked
 * against the shape this build was generated for (ecu_build.h): a model or tuning of
 * another shape is refused with both shapes named, never silently truncated.
 */
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "ecu_config.h"
#include "ecu_contract.h"
#include "ecu_pyfloat.h"

#define NAME_BYTES 48
#define N_TUNING_VALUES 38
#define MAX_RECORD_VALUES (ECU_NK * ECU_NZ * ECU_NZ > ECU_ENCODER_MAX ? ECU_NK * ECU_NZ * ECU_NZ : ECU_ENCODER_MAX)

/* The bit of record koopman.N in ecu_read_data's `seen` (after the encoder's records). */
#define BILINEAR_BIT (13 + 2 * ECU_N_LAYERS)

static const char *const CONTROLLER_NAMES[ECU_N_CONTROLLERS] = {"eso-dkmpc", "dkmpc", "lmpc"};

/* One record as read: name, rank, dims and values (static: no heap). */
static char rec_name[NAME_BYTES + 1];
static uint32_t rec_rank, rec_dims[4];
static double rec_values[MAX_RECORD_VALUES];

static void format_shape(char *buf, size_t len, uint32_t rank, const uint32_t *dims) {
  size_t used = (size_t)snprintf(buf, len, "(");
  for (uint32_t i = 0; i < rank && used < len; i++)
    used += (size_t)snprintf(buf + used, len - used, i + 1 < rank || rank == 1 ? "%u," : "%u", dims[i]);
  if (used < len) snprintf(buf + used, len - used, ")");
}

/* Wanted shape of each record; 0 when the name is known, -1 (err set) otherwise. */
static int check_shape(const char *path, uint32_t rank, const uint32_t *dims, char *err, size_t err_len) {
  char got[64], want[64];
  if (rec_rank != rank || memcmp(rec_dims, dims, rank * sizeof(uint32_t)) != 0) {
    format_shape(got, sizeof got, rec_rank, rec_dims);
    format_shape(want, sizeof want, rank, dims);
    snprintf(err, err_len, "%s: record %s has shape %s, this build needs %s", path, rec_name, got, want);
    return -1;
  }
  return 0;
}

static int read_tuning(const char *path, int id, ecu_tuning_t *t, char *err, size_t err_len) {
  const uint32_t dims[1] = {N_TUNING_VALUES};
  static const int BUILD_NP[ECU_N_CONTROLLERS] = {ECU_NP_ESO_DKMPC, ECU_NP_DKMPC, ECU_NP_LMPC};
  static const int BUILD_NC[ECU_N_CONTROLLERS] = {ECU_NC_ESO_DKMPC, ECU_NC_DKMPC, ECU_NC_LMPC};
  const double *v = rec_values;
  if (check_shape(path, 1, dims, err, err_len) != 0) return -1;
  t->n_pred = (int)v[0];
  t->n_ctrl = (int)v[1];
  if (t->n_pred != BUILD_NP[id] || t->n_ctrl != BUILD_NC[id]) {
    snprintf(err, err_len, "%s: [%s] horizons (Np %d, Nc %d) differ from this build's (Np %d, Nc %d)",
             path, CONTROLLER_NAMES[id], t->n_pred, t->n_ctrl, BUILD_NP[id], BUILD_NC[id]);
    return -1;
  }
  t->q_position = v[2];
  t->q_yaw = v[3];
  t->r_steer = v[4];
  t->p_steer_rate = v[5];
  memcpy(t->state_min, v + 6, sizeof t->state_min);
  memcpy(t->state_max, v + 9, sizeof t->state_max);
  t->slack_l1 = v[12];
  t->slack_l2 = v[13];
  t->max_iter = (int)v[14];
  t->eps_abs = v[15];
  t->eps_rel = v[16];
  t->eso_pole = v[17];
  t->eso_second_pole = v[18];
  t->disturbance_decay = v[19];
  t->low_q_position = v[20];
  t->low_q_yaw = v[21];
  t->low_r_steer = v[22];
  t->schedule_low = v[23];
  t->schedule_high = v[24];
  t->eso_innovation_limit = v[25];
  t->yaw_rate_bias_pole = v[26];
  t->slip_target_limit = v[27];
  t->slip_target_gate = v[28];
  t->qp_steer_rate_limit = v[29];
  t->delay_compensation_s = v[30];
  t->eso_innovation_persistence = v[31];
  t->eso_widening_lateral_accel = v[32];
  t->pose_heading_advance = v[33];
  t->grip_slip_excess = v[34];
  t->grip_margin = v[35];
  t->grip_recovery = v[36];
  t->grip_peak_time = v[37];
  for (int i = 2; i < N_TUNING_VALUES; i++) {
    if ((i >= 17 && i < 20) || i == 25 || i == 26 || i == 31 || i == 32) continue; /* the observer fields: NaN where the table has none */
    if (!isfinite(v[i])) {
      snprintf(err, err_len, "%s: [%s] value %d is not finite", path, CONTROLLER_NAMES[id], i);
      return -1;
    }
  }
  /* The ranges of controller/tuning.py's _RULES: the same verdict as the Python loader. */
  if (!(t->qp_steer_rate_limit >= 0.0 && t->qp_steer_rate_limit <= 100.0)) {
    snprintf(err, err_len, "%s: [%s] qp_steer_rate_limit must be in [0, 100] rad/s (0: off), got %g", path,
             CONTROLLER_NAMES[id], t->qp_steer_rate_limit);
    return -1;
  }
  if (!(t->delay_compensation_s >= 0.0 && t->delay_compensation_s <= 0.1)) {
    snprintf(err, err_len, "%s: [%s] delay_compensation_s must be in [0, 0.1] s (0: off), got %g", path,
             CONTROLLER_NAMES[id], t->delay_compensation_s);
    return -1;
  }
  if (!(t->pose_heading_advance == 0.0 || t->pose_heading_advance == 0.5)) {
    snprintf(err, err_len,
             "%s: [%s] pose_heading_advance must be 0 (eq. 20, explicit Euler) or 0.5 (the step's midpoint), got %g",
             path, CONTROLLER_NAMES[id], t->pose_heading_advance);
    return -1;
  }
  /* The grip envelope's fields, with the rule's text and the value as Python's repr: the
   * Python loader's message word for word. */
  const struct {
    const char *name, *rule;
    double value;
    int ok;
  } grip_fields[4] = {
      {"grip_slip_excess", "must be in [0, 0.2] rad (0: off)", t->grip_slip_excess,
       t->grip_slip_excess >= 0.0 && t->grip_slip_excess <= 0.2},
      {"grip_margin", "must be in [0, 2]", t->grip_margin, t->grip_margin >= 0.0 && t->grip_margin <= 2.0},
      {"grip_recovery", "must be in (0, 1000] m/s^2 per s", t->grip_recovery,
       t->grip_recovery > 0.0 && t->grip_recovery <= 1000.0},
      {"grip_peak_time", "must be in (0, 60] s", t->grip_peak_time,
       t->grip_peak_time > 0.0 && t->grip_peak_time <= 60.0}};
  for (int i = 0; i < 4; i++) {
    if (grip_fields[i].ok) continue;
    char got[32];
    py_repr(got, sizeof got, grip_fields[i].value);
    snprintf(err, err_len, "%s: [%s] %s %s, got %s", path, CONTROLLER_NAMES[id], grip_fields[i].name,
             grip_fields[i].rule, got);
    return -1;
  }
  if (!(t->schedule_low >= 0.0 && t->schedule_low < t->schedule_high)) {
    snprintf(err, err_len, "%s: [%s] weight_schedule_speeds [%g, %g] must be 0 <= low < high", path,
             CONTROLLER_NAMES[id], t->schedule_low, t->schedule_high);
    return -1;
  }
  return 0;
}

/* Store the record just read into cfg; *seen gets the bit of the record. */
static int store_record(const char *path, ecu_config_t *cfg, unsigned long *seen, char *err, size_t err_len) {
  static const int WIDTHS[] = ECU_LAYER_WIDTHS;
  const uint32_t one[1] = {1};
  if (strcmp(rec_name, "ts") == 0) {
    if (check_shape(path, 1, one, err, err_len)) return -1;
    cfg->ts = rec_values[0];
    *seen |= 1ul << 0;
  } else if (strcmp(rec_name, "longitudinal") == 0) {
    const uint32_t d[1] = {3};
    if (check_shape(path, 1, d, err, err_len)) return -1;
    cfg->speed_gain = rec_values[0];
    cfg->torque_min = rec_values[1];
    cfg->torque_max = rec_values[2];
    *seen |= 1ul << 1;
  } else if (strcmp(rec_name, "bicycle") == 0) {
    const uint32_t d[1] = {6};
    if (check_shape(path, 1, d, err, err_len)) return -1;
    cfg->cf = rec_values[0];
    cfg->cr = rec_values[1];
    cfg->mass = rec_values[2];
    cfg->yaw_inertia = rec_values[3];
    cfg->lf = rec_values[4];
    cfg->lr = rec_values[5];
    *seen |= 1ul << 2;
  } else if (strcmp(rec_name, "grip.axle") == 0) {
    /* Checked after the loop (has_grip_axle), not by a bit: the bits past 13 are the model's. */
    const uint32_t d[1] = {4};
    if (check_shape(path, 1, d, err, err_len)) return -1;
    cfg->grip_mass = rec_values[0];
    cfg->grip_lf = rec_values[1];
    cfg->grip_lr = rec_values[2];
    cfg->grip_cr = rec_values[3];
    cfg->has_grip_axle = 1;
  } else if (strncmp(rec_name, "tuning.", 7) == 0) {
    for (int id = 0; id < ECU_N_CONTROLLERS; id++) {
      if (strcmp(rec_name + 7, CONTROLLER_NAMES[id]) == 0) {
        if (read_tuning(path, id, &cfg->tuning[id], err, err_len)) return -1;
        *seen |= 1ul << (3 + id);
      }
    }
  } else if (strcmp(rec_name, "koopman.form") == 0) {
    if (check_shape(path, 1, one, err, err_len)) return -1;
    cfg->form = (int)rec_values[0];
    if (cfg->form != ECU_FORM) {
      snprintf(err, err_len, "%s: record koopman.form is %d, this build needs %d (0 linear, 2 scheduled, "
               "3 scheduled with the steer-bilinear term)",
               path, cfg->form, ECU_FORM);
      return -1;
    }
    *seen |= 1ul << 6;
  } else if (strcmp(rec_name, "koopman.knots") == 0) {
    const uint32_t d[1] = {ECU_NK};
    if (check_shape(path, 1, d, err, err_len)) return -1;
    memcpy(cfg->knots, rec_values, sizeof cfg->knots);
    *seen |= 1ul << 7;
  } else if (strcmp(rec_name, "koopman.A") == 0) {
    const uint32_t d[3] = {ECU_NK, ECU_NZ, ECU_NZ};
    if (check_shape(path, 3, d, err, err_len)) return -1;
    memcpy(cfg->A, rec_values, sizeof cfg->A);
    *seen |= 1ul << 8;
  } else if (strcmp(rec_name, "koopman.B") == 0) {
    const uint32_t d[3] = {ECU_NK, ECU_NZ, ECU_NU};
    if (check_shape(path, 3, d, err, err_len)) return -1;
    memcpy(cfg->B, rec_values, sizeof cfg->B);
    *seen |= 1ul << 9;
  } else if (strcmp(rec_name, "koopman.offset") == 0) {
    const uint32_t d[2] = {ECU_NK, ECU_NZ};
    if (check_shape(path, 2, d, err, err_len)) return -1;
    memcpy(cfg->offset, rec_values, sizeof cfg->offset);
    *seen |= 1ul << 10;
#if ECU_BILINEAR
  } else if (strcmp(rec_name, "koopman.N") == 0) {
    const uint32_t d[3] = {ECU_NK, ECU_NZ, ECU_NZ};
    if (check_shape(path, 3, d, err, err_len)) return -1;
    memcpy(cfg->N, rec_values, sizeof cfg->N);
    *seen |= 1ul << BILINEAR_BIT;
#endif
  } else if (strcmp(rec_name, "koopman.state_fields") == 0) {
    const uint32_t d[1] = {ECU_NX};
    if (check_shape(path, 1, d, err, err_len)) return -1;
    for (int i = 0; i < ECU_NX; i++) {
      cfg->state_fields[i] = (int)rec_values[i];
      if (cfg->state_fields[i] < 0 || cfg->state_fields[i] > 8) {
        snprintf(err, err_len, "%s: koopman.state_fields[%d] = %d is not a sample field", path, i,
                 cfg->state_fields[i]);
        return -1;
      }
    }
    *seen |= 1ul << 11;
  } else if (strcmp(rec_name, "koopman.dictionary") == 0) {
    const uint32_t d[1] = {ECU_NDICT};
    if (check_shape(path, 1, d, err, err_len)) return -1;
    for (int i = 0; i < ECU_NDICT; i++) cfg->dictionary[i] = (int)rec_values[i];
    *seen |= 1ul << 12;
  } else if (rec_name[0] == 'k' && strncmp(rec_name, "koopman.", 8) == 0 &&
             (rec_name[8] == 'w' || rec_name[8] == 'b')) {
    int layer = -1;
    char tail = 0;
    if (sscanf(rec_name + 9, "%d%c", &layer, &tail) != 1 || layer < 0 || layer >= ECU_N_LAYERS) {
      snprintf(err, err_len, "%s: record %s: this build's encoder has %d layers", path, rec_name, ECU_N_LAYERS);
      return -1;
    }
    uint32_t width_in = (uint32_t)(layer == 0 ? ECU_NX : WIDTHS[layer - 1]);
    uint32_t width_out = (uint32_t)WIDTHS[layer];
    if (rec_name[8] == 'w') {
      const uint32_t d[2] = {width_out, width_in};
      if (check_shape(path, 2, d, err, err_len)) return -1;
      /* Stored input-major (transposed, see ecu_config.h): the lift's sums over outputs; as
       * floats where every weight is one exactly (the same numbers once converted back). */
      const uint32_t n = width_out * width_in;
      int single = 1;
      for (uint32_t k = 0; k < n && single; k++)
        single = fabs(rec_values[k]) <= FLT_MAX && (double)(float)rec_values[k] == rec_values[k];
      cfg->weights_single[layer] = single;
      double *w = cfg->weights.value + cfg->weight_at[layer];
      float *w_single = cfg->weights.single + 2 * cfg->weight_at[layer];
      for (uint32_t o = 0; o < width_out; o++)
        for (uint32_t i = 0; i < width_in; i++) {
          if (single) w_single[i * width_out + o] = (float)rec_values[o * width_in + i];
          else w[i * width_out + o] = rec_values[o * width_in + i];
        }
      *seen |= 1ul << (13 + layer);
    } else {
      const uint32_t d[1] = {width_out};
      if (check_shape(path, 1, d, err, err_len)) return -1;
      memcpy(cfg->biases + cfg->bias_at[layer], rec_values, width_out * sizeof(double));
      *seen |= 1ul << (13 + ECU_N_LAYERS + layer);
    }
  }
  /* Other records: written by a newer tool, not needed by this build. */
  return 0;
}

static const char *form_name(int form) {
  switch (form) {
    case 0: return "linear";
    case 2: return "scheduled";
    case 3: return "scheduled bilinear";
    default: return "unknown";
  }
}

int ecu_read_data(const char *path, ecu_config_t *cfg, char *err, size_t err_len) {
  static const int WIDTHS[] = ECU_LAYER_WIDTHS;
  char magic[8];
  uint32_t count = 0;
  /* every record: the 13 named ones, the encoder's, and koopman.N in a bilinear build */
  unsigned long seen = 0, wanted = (1ul << (BILINEAR_BIT + ECU_BILINEAR)) - 1ul;
  int weight_at = 0, bias_at = 0;
  int model_mismatch = 0, file_form = -1, file_knots = 0, file_nz = 0;
  char detail[200] = "";
  memset(cfg, 0, sizeof *cfg);
  for (int i = 0; i < ECU_N_LAYERS; i++) {
    cfg->layer_in[i] = i == 0 ? ECU_NX : WIDTHS[i - 1];
    cfg->layer_out[i] = WIDTHS[i];
    cfg->weight_at[i] = weight_at;
    cfg->bias_at[i] = bias_at;
    weight_at += cfg->layer_in[i] * cfg->layer_out[i];
    bias_at += cfg->layer_out[i];
  }
  FILE *file = fopen(path, "rb");
  if (!file) {
    snprintf(err, err_len, "%s: cannot open the ECU data file (make firmware writes it)", path);
    return -1;
  }
  int status = 0;
  if (fread(magic, 1, 8, file) != 8 || memcmp(magic, "ECUDATA1", 8) != 0 || fread(&count, 4, 1, file) != 1) {
    snprintf(err, err_len, "%s: not an ECU data file (magic ECUDATA1 missing)", path);
    status = -1;
  }
  for (uint32_t r = 0; status == 0 && r < count; r++) {
    uint32_t head[5];
    size_t n = 1;
    if (fread(rec_name, 1, NAME_BYTES, file) != NAME_BYTES || fread(head, 4, 5, file) != 5) {
      snprintf(err, err_len, "%s: truncated at record %u", path, r);
      status = -1;
      break;
    }
    rec_name[NAME_BYTES] = '\0';
    rec_rank = head[0];
    if (rec_rank > 4) {
      snprintf(err, err_len, "%s: record %s has rank %u (at most 4)", path, rec_name, rec_rank);
      status = -1;
      break;
    }
    for (int i = 0; i < 4; i++) {
      rec_dims[i] = head[1 + i];
      if (i < (int)rec_rank) n *= rec_dims[i];
    }
    int is_model = strncmp(rec_name, "koopman.", 8) == 0;
    if (strcmp(rec_name, "koopman.A") == 0 && rec_rank == 3) {
      file_knots = (int)rec_dims[0];
      file_nz = (int)rec_dims[1];
    }
    if (n > MAX_RECORD_VALUES) {
      /* Larger than anything this build stores: its shape cannot be the build's. */
      if (fseek(file, (long)(n * sizeof(double)), SEEK_CUR) != 0) {
        snprintf(err, err_len, "%s: truncated in record %s", path, rec_name);
        status = -1;
        break;
      }
      rec_values[0] = NAN;
      if (is_model && !model_mismatch) {
        snprintf(detail, sizeof detail, "record %s holds %zu values", rec_name, n);
        model_mismatch = 1;
      } else if (strncmp(rec_name, "tuning.", 7) == 0) {
        snprintf(err, err_len, "%s: record %s holds %zu values, more than any shape of this build", path,
                 rec_name, n);
        status = -1;
      }
      continue;
    }
    if (fread(rec_values, sizeof(double), n, file) != n) {
      snprintf(err, err_len, "%s: truncated in record %s", path, rec_name);
      status = -1;
      break;
    }
    if (strncmp(rec_name, "tuning.", 7) != 0) { /* a tuning record's observer fields may be NaN */
      size_t bad = 0;
      while (bad < n && isfinite(rec_values[bad])) bad++;
      if (bad < n) {
        snprintf(err, err_len, "%s: record %s: value %zu is not finite (%g)", path, rec_name, bad, rec_values[bad]);
        status = -1;
        break;
      }
    }
    if (strcmp(rec_name, "koopman.form") == 0 && n == 1) file_form = (int)rec_values[0];
    if (is_model) {
      /* A model of another shape: read on, then name both shapes (below). */
      char record_err[300];
      if (store_record(path, cfg, &seen, record_err, sizeof record_err) != 0 && !model_mismatch) {
        const char *what = strstr(record_err, "record ");
        snprintf(detail, sizeof detail, "%s", what ? what : "model form");
        model_mismatch = 1;
      }
    } else {
      status = store_record(path, cfg, &seen, err, err_len);
    }
  }
  fclose(file);
  if (status == 0 && model_mismatch) {
    snprintf(err, err_len, "%s: the model's shape (form %s, %d knots, n_z %d) differs from this build's "
             "(form %s, %d knots, n_z %d): %.150s; rebuild with make firmware for this model", path,
             form_name(file_form), file_knots, file_nz, form_name(ECU_FORM), ECU_NK, ECU_NZ, detail);
    status = -1;
  }
  if (status == 0 && !cfg->has_grip_axle) {
    snprintf(err, err_len, "%s: record grip.axle missing", path);
    status = -1;
  }
  if (status == 0 && (seen & wanted) != wanted) {
    static const char *const NAMES[13] = {"ts", "longitudinal", "bicycle", "tuning.eso-dkmpc", "tuning.dkmpc",
                                          "tuning.lmpc", "koopman.form", "koopman.knots", "koopman.A",
                                          "koopman.B", "koopman.offset", "koopman.state_fields",
                                          "koopman.dictionary"};
    int missing = 0;
    while (seen & (1ul << missing)) missing++;
    if (missing < 13)
      snprintf(err, err_len, "%s: record %s missing", path, NAMES[missing]);
    else if (missing == BILINEAR_BIT)
      snprintf(err, err_len, "%s: record koopman.N missing (this build is for the scheduled form with the "
               "steer-bilinear term N(v))", path);
    else {
      /* The encoder's bits: w0..w(L-1), then b0..b(L-1). No `% ECU_N_LAYERS`: a build without
       * encoder layers (edmdc-linear) has L = 0 and never gets here, but must still compile. */
      int layer = missing - 13, is_bias = layer >= ECU_N_LAYERS;
      snprintf(err, err_len, "%s: encoder record koopman.%c%d missing (this build's encoder has %d layers)",
               path, is_bias ? 'b' : 'w', is_bias ? layer - ECU_N_LAYERS : layer, ECU_N_LAYERS);
    }
    status = -1;
  }
  /* The MPC steps the model once a control period and the pose prediction uses ts: a model
   * of another sample time would steer otherwise (controller/registry.py check_ecu_model_ts,
   * the same text and tolerance). */
  if (status == 0 && !(fabs(cfg->ts - CONTROL_PERIOD_MS / 1000.0) <= 1e-9)) {
    snprintf(err, err_len, "%s: the model's sample time ts %g s differs from the control period %g s "
             "(train it with --ts %g)", path, cfg->ts, CONTROL_PERIOD_MS / 1000.0, CONTROL_PERIOD_MS / 1000.0);
    status = -1;
  }
  if (status == 0 && !(cfg->ts > 0.0 && cfg->torque_min < cfg->torque_max && cfg->mass > 0.0 &&
                       cfg->yaw_inertia > 0.0)) {
    snprintf(err, err_len, "%s: ts, torque limits or bicycle parameters out of range", path);
    status = -1;
  }
  return status;
}

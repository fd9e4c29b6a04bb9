// Obstacle avoider (subsumption layer, default priority 3), in C.
//
// The same component as guest-components/rust/avoider: the same ports,
// parameters, description and commands (tests/all/languages.rs checks it).
// Reads a range scan whose rays are spread evenly from -fov/2 (right) to
// +fov/2 (left) of the heading. While an obstacle inside the front cone is
// nearer than `threshold`, it emits `VEL <creep> <turn>` on every tick,
// turning toward the freer side. Otherwise it stays silent: silence tells the
// arbiter this behaviour is not active, so a lower layer drives.
//
// Ownership (the canonical ABI's rules, as wit-bindgen's C bindings expose
// them): arguments handed to an export belong to the component, which frees
// them; strings and lists an export returns are freed by the generated
// post-return code, so they must come from malloc (component_string_dup).

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "component.h"

static struct {
  bool ready;
  double threshold, fov, cone, turn_rate, creep_speed;
  component_list_f64_t ranges;
} self;

static void port(subsume_robot_types_port_spec_t *p, const char *name, subsume_robot_types_value_kind_t kind,
                 const char *doc) {
  component_string_dup(&p->name, name);
  p->kind = kind;
  component_string_dup(&p->doc, doc);
}

static void param(subsume_robot_types_param_spec_t *p, const char *name, const char *default_value,
                  const char *doc) {
  component_string_dup(&p->name, name);
  p->kind = SUBSUME_ROBOT_TYPES_PARAM_KIND_NUMBER;
  component_string_dup(&p->default_value, default_value);
  component_string_dup(&p->doc, doc);
}

void exports_component_describe(component_description_t *ret) {
  component_string_dup(&ret->name, "avoider");
  component_string_dup(&ret->version, "0.1.0");
  component_string_dup(&ret->summary, "Turns away from obstacles nearer than a threshold");
  ret->inputs.len = 1;
  ret->inputs.ptr = malloc(sizeof *ret->inputs.ptr);
  port(&ret->inputs.ptr[0], "ranges", SUBSUME_ROBOT_TYPES_VALUE_KIND_VECTOR,
       "ranges in metres, rays from -fov/2 (right) to +fov/2 (left)");
  ret->outputs.len = 1;
  ret->outputs.ptr = malloc(sizeof *ret->outputs.ptr);
  port(&ret->outputs.ptr[0], "cmd", SUBSUME_ROBOT_TYPES_VALUE_KIND_COMMAND,
       "VEL commands while an obstacle is near; silent otherwise");
  ret->params.len = 5;
  ret->params.ptr = malloc(5 * sizeof *ret->params.ptr);
  param(&ret->params.ptr[0], "threshold", "0.5", "an obstacle nearer than this (metres) triggers avoidance");
  param(&ret->params.ptr[1], "fov", "3.14159", "angle covered by the scan, radians");
  param(&ret->params.ptr[2], "cone", "1.6", "width of the front cone that is watched, radians");
  param(&ret->params.ptr[3], "turn-rate", "1.2", "turn rate while avoiding, rad/s");
  param(&ret->params.ptr[4], "creep-speed", "0.0", "forward speed while avoiding, m/s");
  ret->default_priority.is_some = true;
  ret->default_priority.val = 3;
}

// Puts `message` into `err` (freed by post-return) and reports failure.
static bool fail(component_string_t *err, const char *message) {
  component_string_dup(err, message);
  return false;
}

// Parameter `name` as a number; the host has already checked its kind.
static bool number(const component_list_param_t *params, const char *name, double *out, component_string_t *err) {
  char message[160];
  for (size_t i = 0; i < params->len; i++) {
    const component_string_t *key = &params->ptr[i].name;
    if (key->len != strlen(name) || memcmp(key->ptr, name, key->len) != 0) {
      continue;
    }
    const component_string_t *value = &params->ptr[i].value;
    char *text = calloc(value->len + 1, 1);
    memcpy(text, value->ptr, value->len);
    char *end = text;
    *out = strtod(text, &end);
    while (*end == ' ' || *end == '\t' || *end == '\n' || *end == '\r') {
      end++;
    }
    bool ok = end != text && *end == '\0';
    if (!ok) {
      snprintf(message, sizeof message, "parameter '%s': '%.64s' is not a number", name, text);
    }
    free(text);
    return ok || fail(err, message);
  }
  snprintf(message, sizeof message, "missing parameter '%s'", name);
  return fail(err, message);
}

bool exports_component_init(component_list_param_t *params, component_string_t *err) {
  bool ok = number(params, "threshold", &self.threshold, err) && number(params, "fov", &self.fov, err) &&
            number(params, "cone", &self.cone, err) && number(params, "turn-rate", &self.turn_rate, err) &&
            number(params, "creep-speed", &self.creep_speed, err);
  component_list_param_free(params);
  if (ok && (self.threshold <= 0.0 || self.fov <= 0.0 || self.cone <= 0.0)) {
    ok = fail(err, "threshold, fov and cone must be positive");
  }
  self.ready = ok;
  return ok;
}

bool exports_component_on_input(uint32_t port, component_value_t *value, component_string_t *err) {
  (void)port;
  if (!self.ready) {
    component_value_free(value);
    return fail(err, "on-input called before init");
  }
  if (value->tag != SUBSUME_ROBOT_TYPES_VALUE_VECTOR) {
    component_value_free(value);
    return fail(err, "ranges: expected a vector");
  }
  // Keep the list itself: it is ours now.
  component_list_f64_free(&self.ranges);
  self.ranges = value->val.vector;
  return true;
}

bool exports_component_tick(uint64_t now_ns, component_string_t *err) {
  (void)now_ns;
  if (!self.ready) {
    return fail(err, "tick called before init");
  }
  size_t n = self.ranges.len;
  if (n == 0) {
    return true;
  }
  double step = n > 1 ? self.fov / (double)(n - 1) : 0.0;
  bool near = false;
  double left = 0.0, right = 0.0;
  for (size_t i = 0; i < n; i++) {
    double r = self.ranges.ptr[i];
    double angle = -self.fov / 2.0 + step * (double)i;
    if (fabs(angle) <= self.cone / 2.0 && r < self.threshold) {
      near = true;
    }
    if (angle > 0.0) {
      left += r;
    } else if (angle < 0.0) {
      right += r;
    }
  }
  if (near) {
    double turn = left >= right ? self.turn_rate : -self.turn_rate;
    // Numbers may be as long as the host lets a parameter be: size first.
    int len = snprintf(NULL, 0, "VEL %.3f %.3f", self.creep_speed, turn);
    char *text = malloc((size_t)len + 1);
    snprintf(text, (size_t)len + 1, "VEL %.3f %.3f", self.creep_speed, turn);
    subsume_robot_host_value_t cmd = {.tag = SUBSUME_ROBOT_TYPES_VALUE_COMMAND};
    component_string_set(&cmd.val.command, text);
    subsume_robot_host_emit(0, &cmd);
    free(text);
  }
  return true;
}

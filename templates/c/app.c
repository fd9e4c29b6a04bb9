// {{name}}: a subsume robot component, made by `subsume new`.
//
// A starting point that already drives a robot: while something in the
// front cone (`cone` radians wide, centred on the heading) is nearer than
// `threshold`, it emits `VEL <creep-speed> <turn>` on every tick, turning
// toward the side whose nearest reading is farther; otherwise it stays
// silent, and a lower-priority source drives. The rays spread evenly over
// `fov` from right to left. Its ports and parameters match the demo's
// obstacle avoider, so it can take that one's place in subsume's
// config/demo.xml, and passes the lab's preflight there unchanged.
//
// build/component.h (made by wit-bindgen from wit/robot.wit) declares the
// exports to write and the host functions to call. Ownership follows the
// canonical ABI: what an export receives is yours to free; what it returns
// (strings, lists) is freed after the call, so it must come from malloc.

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "component.h"

static double threshold = 0.5, fov = 3.14159, cone = 1.6, turn_rate = 1.2, creep_speed = 0.0;
static component_list_f64_t ranges;

static void port(subsume_robot_types_list_port_spec_t *list, const char *name, subsume_robot_types_value_kind_t kind,
                 const char *doc) {
  list->len = 1;
  list->ptr = malloc(sizeof *list->ptr);
  component_string_dup(&list->ptr[0].name, name);
  list->ptr[0].kind = kind;
  component_string_dup(&list->ptr[0].doc, doc);
}

static void param(subsume_robot_types_param_spec_t *p, const char *name, const char *value, const char *doc) {
  component_string_dup(&p->name, name);
  p->kind = SUBSUME_ROBOT_TYPES_PARAM_KIND_NUMBER;
  component_string_dup(&p->default_value, value);
  component_string_dup(&p->doc, doc);
}

// Declared once: the host reads it before `init` to check the wiring.
void exports_component_describe(component_description_t *ret) {
  component_string_dup(&ret->name, "{{name}}");
  component_string_dup(&ret->version, "0.1.0");
  component_string_dup(&ret->summary, "Turns away from what is close in front");
  port(&ret->inputs, "ranges", SUBSUME_ROBOT_TYPES_VALUE_KIND_VECTOR, "ranges in metres, rays from -fov/2 (right) to +fov/2 (left)");
  port(&ret->outputs, "cmd", SUBSUME_ROBOT_TYPES_VALUE_KIND_COMMAND,
       "VEL commands while something is close; silent otherwise");
  ret->params.len = 5;
  ret->params.ptr = malloc(5 * sizeof *ret->params.ptr);
  param(&ret->params.ptr[0], "threshold", "0.5", "nearer than this in front (metres) is too close");
  param(&ret->params.ptr[1], "fov", "3.14159", "angle the rays cover, radians");
  param(&ret->params.ptr[2], "cone", "1.6", "width of the watched front cone, radians");
  param(&ret->params.ptr[3], "turn-rate", "1.2", "turn rate while turning away, rad/s");
  param(&ret->params.ptr[4], "creep-speed", "0.0", "forward speed while turning away, m/s");
  ret->default_priority.is_some = true;
  ret->default_priority.val = 3;
}

// Every declared parameter arrives, already checked against its kind.
bool exports_component_init(component_list_param_t *params, component_string_t *err) {
  (void)err;
  for (size_t i = 0; i < params->len; i++) {
    char name[32] = {0}, value[64] = {0};
    component_param_t *p = &params->ptr[i];
    memcpy(name, p->name.ptr, p->name.len < sizeof name - 1 ? p->name.len : sizeof name - 1);
    memcpy(value, p->value.ptr, p->value.len < sizeof value - 1 ? p->value.len : sizeof value - 1);
    double number = strtod(value, NULL);
    if (strcmp(name, "threshold") == 0) threshold = number;
    if (strcmp(name, "fov") == 0) fov = number;
    if (strcmp(name, "cone") == 0) cone = number;
    if (strcmp(name, "turn-rate") == 0) turn_rate = number;
    if (strcmp(name, "creep-speed") == 0) creep_speed = number;
  }
  component_list_param_free(params);
  if (!(fov > 0.0 && cone > 0.0)) {
    component_string_dup(err, "fov and cone must be positive");  // refuses to start
    return false;
  }
  char line[128];
  snprintf(line, sizeof line, "ready: turning away from anything nearer than %g m", threshold);
  component_string_t message;
  component_string_set(&message, line);
  subsume_robot_host_log(SUBSUME_ROBOT_TYPES_LOG_LEVEL_INFO, &message);
  return true;
}

bool exports_component_on_input(uint32_t port, component_value_t *value, component_string_t *err) {
  (void)port;
  (void)err;
  if (value->tag == SUBSUME_ROBOT_TYPES_VALUE_VECTOR) {
    component_list_f64_free(&ranges);
    ranges = value->val.vector;  // keep the list: it is ours
  } else {
    component_value_free(value);
  }
  return true;
}

// The nearest reading among the rays whose angle (counter-clockwise from
// ahead, evenly over fov) lies in [from, to].
static double nearest(double from, double to) {
  double least = INFINITY, step = ranges.len > 1 ? fov / (double)(ranges.len - 1) : 0.0;
  for (size_t i = 0; i < ranges.len; i++) {
    double angle = -fov / 2 + step * (double)i;
    if (angle >= from && angle <= to) least = fmin(least, ranges.ptr[i]);
  }
  return least;
}

bool exports_component_tick(uint64_t now_ns, component_string_t *err) {
  (void)now_ns;
  (void)err;
  if (nearest(-cone / 2, cone / 2) < threshold) {
    // Left: angles above 0; right: below (a ray straight ahead is neither).
    double turn = nearest(1e-9, INFINITY) >= nearest(-INFINITY, -1e-9) ? turn_rate : -turn_rate;
    char text[96];
    snprintf(text, sizeof text, "VEL %.3f %.3f", creep_speed, turn);
    subsume_robot_host_value_t cmd = {.tag = SUBSUME_ROBOT_TYPES_VALUE_COMMAND};
    component_string_set(&cmd.val.command, text);
    subsume_robot_host_emit(0, &cmd);
  }
  return true;
}

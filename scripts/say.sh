# Sourced by the scripts: `say TEXT` prints a step on stderr, in bold only
# on a terminal and without NO_COLOR (no-color.org), so a redirected log
# holds plain text.
say() {
  if [ -t 2 ] && [ -z "${NO_COLOR:-}" ]; then
    printf '\033[1m==> %s\033[0m\n' "$*" >&2
  else
    printf '==> %s\n' "$*" >&2
  fi
}

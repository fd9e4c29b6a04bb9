# Sourced by the scripts: `say TEXT` prints a step on stderr, in bold only
# on a terminal and without NO_COLOR (no-color.org), so a redirected log
# holds plain text. Each step carries the minutes and seconds since the
# outermost script began (SAY_T0, exported to the scripts it runs), so a
# CI log shows where its time went.
if [ -z "${SAY_T0:-}" ]; then
  SAY_T0=$(date +%s)
  export SAY_T0
fi
say() {
  local elapsed=$(($(date +%s) - SAY_T0))
  local stamp
  stamp=$(printf '%d:%02d' $((elapsed / 60)) $((elapsed % 60)))
  if [ -t 2 ] && [ -z "${NO_COLOR:-}" ]; then
    printf '\033[1m==> [%s] %s\033[0m\n' "$stamp" "$*" >&2
  else
    printf '==> [%s] %s\n' "$stamp" "$*" >&2
  fi
}

# What the bench scripts share: their command-line parsing. Sourced by them (`. "$(dirname "$0")/lib.sh"`),
# not run; it defines functions only.

# bench_fail SCRIPT MESSAGE: say MESSAGE as SCRIPT on stderr and exit 2 (a usage error).
bench_fail() {
  echo "$1: $2" >&2
  exit 2
}

# bench_parse SCRIPT HELP SPEC... -- ARG...: parse the script's arguments ARG... as the SPECs say, setting the
# script's variables (which hold their defaults beforehand). A SPEC is one of
#   --opt=VAR       VAR takes the argument after --opt
#   --opt+=ARRAY    the argument after --opt is appended to the array ARRAY (a repeatable option)
#   --opt@=VAR      --opt itself is appended to the string VAR, after a space (a flag passed on to a command)
#   LABEL=BINARY    an argument LABEL=BINARY is appended to the array BINS
# -h or --help prints the lines HELP (a sed range, such as 2,18) of the script and exits 0; any other argument
# is a usage error (exit 2).
bench_parse() {
  local _script=$1 _help=$2 _specs=() _spec _opt _kind _var _found
  shift 2
  while [ $# -gt 0 ] && [ "$1" != -- ]; do
    _specs+=("$1")
    shift
  done
  [ $# -gt 0 ] && shift
  while [ $# -gt 0 ]; do
    case "$1" in
      -h|--help) sed -n "${_help}p" "$0"; exit 0 ;;
    esac
    _found=
    for _spec in "${_specs[@]}"; do
      case "$_spec" in
        LABEL=BINARY) continue ;;
        *+=*) _opt=${_spec%%+=*} _kind=append _var=${_spec#*+=} ;;
        *@=*) _opt=${_spec%%@=*} _kind=flag _var=${_spec#*@=} ;;
        *=*) _opt=${_spec%%=*} _kind=set _var=${_spec#*=} ;;
        *) bench_fail "$_script" "bench_parse: bad spec $_spec" ;;
      esac
      [ "$_opt" = "$1" ] || continue
      _found=1
      if [ "$_kind" = flag ]; then
        printf -v "$_var" '%s %s' "${!_var}" "$1"
        break
      fi
      [ $# -ge 2 ] || bench_fail "$_script" "$1 needs a value"
      if [ "$_kind" = set ]; then
        printf -v "$_var" '%s' "$2"
      else
        eval "$_var+=(\"\$2\")"
      fi
      shift
      break
    done
    if [ -z "$_found" ]; then
      if [[ "$1" == *=* && " ${_specs[*]} " == *" LABEL=BINARY "* ]]; then
        BINS+=("$1")
      else
        bench_fail "$_script" "unknown argument $1"
      fi
    fi
    shift
  done
}

# bench_need_bins SCRIPT: a usage error unless the arguments named at least one LABEL=BINARY.
bench_need_bins() {
  [ ${#BINS[@]} -gt 0 ] || bench_fail "$1" "give at least one LABEL=BINARY"
}

# bench_start SCRIPT WORK NAME CMD...: start CMD in the background pinned as the caller's array `pin` says
# (a server), its output in WORK/NAME.out and its pid appended to WORK/pids (the caller's cleanup stops
# them); wait (at most 5 s) for its "listening ... HOST:PORT" line and print HOST:PORT, or say SCRIPT could
# not start it and exit 1.
bench_start() {
  local script=$1 work=$2 name=$3 a
  shift 3
  "${pin[@]}" "$@" >"$work/$name.out" 2>&1 &
  echo $! >>"$work/pids"
  for _ in $(seq 100); do
    a=$(grep -oE 'listening[^0-9]*[0-9.]+:[0-9]+' "$work/$name.out" | grep -oE '[0-9.]+:[0-9]+$' | head -1 || true)
    if [ -n "$a" ]; then echo "$a"; return; fi
    sleep 0.05
  done
  echo "$script: $name did not start: $(cat "$work/$name.out")" >&2
  exit 1
}

# bench_servers_workdir SCRIPT: set `work` to a new temporary directory for SCRIPT's servers (see
# bench_start), and at exit stop every process whose pid is in $work/pids and remove it; INT and TERM exit
# 130 (through the EXIT trap).
bench_servers_workdir() {
  work=$(mktemp -d "${TMPDIR:-/tmp}/${1%.sh}.XXXXXX")
  trap '[ -f "$work/pids" ] && while read -r p; do kill "$p" 2>/dev/null || true; done <"$work/pids"; rm -rf "$work"' EXIT
  trap 'exit 130' INT TERM
}

# bench_verdict FILE: a run's RESULT line (verdict and counts) from its output FILE, or the first error line
# when it has none, and how many parameters it left NOT RESTORED.
bench_verdict() {
  local r laf
  r=$(grep -h '^RESULT' "$1" | tail -1 | sed 's/^RESULT: //')
  [ -n "$r" ] || r="no result: $(grep -h '^error' "$1" | head -1 | cut -c1-90)"
  laf=$(grep -c 'NOT RESTORED' "$1" || true)
  [ "$laf" = 0 ] || r="$r; $laf NOT RESTORED"
  echo "$r"
}

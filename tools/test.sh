#!/usr/bin/env bash
# `make test`'s pytest part (docs/development.md, Tests). Arguments go to every pytest run.
#
# 1. The tests that start processes, with the Makefile's pytest-xdist options (its PARALLEL:
#    WORKERS workers, a module per worker),
#    and beside them, in a pytest session of its own at nice 19 with the same xdist options,
#    the tests marked `in_process` (the model's computations, about a third of the suite's
#    CPU): they take the CPU the process tests leave idle on either core while those wait
#    on DDS and on simulated devices, and a process on a deadline (the simulated AVR, a
#    driver's 0.5 s reply) keeps its priority. Their output follows the process tests'.
# 2. Then the tests marked `serial` (they measure timing or loss), alone on the machine.
# Exit status: the first failing part's (5, no test selected, counts as a pass).
set -uo pipefail
cd "$(dirname "$0")/.."

read -r -a parallel <<< "${PARALLEL:?the pytest-xdist options (the Makefile passes its PARALLEL)}"
in_process_log=$(mktemp "${TMPDIR:-/tmp}/pma-in-process-tests.XXXXXX")
in_process_pid=
cleanup() {
    [ -n "$in_process_pid" ] && kill -- "-$in_process_pid" 2>/dev/null
    rm -f "$in_process_log"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

passed() { [ "$1" -eq 0 ] || [ "$1" -eq 5 ]; }

# Its own session, so its own scheduling autogroup (Linux's default for a session: the CPU is
# shared between autogroups first), made nice 19 as a whole; where the kernel has no
# autogroups, the process's own nice does the same. Starved by design while the process tests
# are busy (its longest test took 30 s here, 12 s alone), so pytest-timeout's 180 s for hangs
# is 600 s there; a timeout given in the arguments still wins.
PMA_TEST_DOMAINS=102-120 setsid bash -c \
    'echo 19 > /proc/self/autogroup 2>/dev/null; exec nice -n 19 "$@"' in_process \
    python -m pytest "${parallel[@]}" --timeout 600 -m "in_process and not serial" "$@" \
    > "$in_process_log" 2>&1 &
in_process_pid=$!

# The slowest process tests are listed at the end: where `make test`'s time goes, in CI too.
python -m pytest "${parallel[@]}" --durations 15 -m "not in_process and not serial" "$@"
process_status=$?

echo "[test] the in_process tests, run at nice 19 beside those above:"
wait "$in_process_pid"
in_process_status=$?
in_process_pid=
cat "$in_process_log"

python -m pytest -m serial "$@"
serial_status=$?

for status in "$process_status" "$in_process_status" "$serial_status"; do
    passed "$status" || exit "$status"
done
exit 0

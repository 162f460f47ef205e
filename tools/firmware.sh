#!/usr/bin/env bash
# Compile the Arduino Mega 2560 firmware (pma_driver/firmware/pma_firmware/) with the Debian
# AVR toolchain and arduino-mk, print its flash and RAM use, then build the simulator that
# runs that image (pma_sim/simavr/, against Debian's simavr) for
# `ros2 run pma_sim simavr_arduino`. Missing packages are installed first with apt-get.
# `make firmware` (so `make test`) and the firmware tests run this.
#
# Exit status: 0 built; 1 compile or link error (or the image does not fit); 3 the AVR
# toolchain is absent and cannot be installed here (not root, no apt-get, or the install
# failed); 4 the firmware built but simavr is absent and cannot be installed. The tests
# report 3 and 4 as skips that say so rather than as failures.
#
# Environment: PMA_FIRMWARE_BUILD_DIR (default <repo>/build/firmware, git-ignored; the image
# is pma_firmware.elf, the simulator simavr/pma_simavr) and PMA_FIRMWARE_DIR (default
# pma_driver/firmware; the tests point it at a broken copy) and PMA_SIMAVR_DIR (default
# pma_sim/simavr, the simulator's source).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
FIRMWARE_DIR="${PMA_FIRMWARE_DIR:-${ROOT}/pma_driver/firmware}"
SIMAVR_DIR="${PMA_SIMAVR_DIR:-${ROOT}/pma_sim/simavr}"
BUILD_DIR="${PMA_FIRMWARE_BUILD_DIR:-${ROOT}/build/firmware}"
ARDUINO_DIR=/usr/share/arduino
APT_PACKAGES=(gcc-avr avr-libc arduino-core-avr arduino-mk)
# libsimavr-dev brings libsimavr2 and libsimavrparts1; simavr is the command-line runner.
SIMAVR_PACKAGES=(simavr libsimavr-dev libsimavrparts1 gcc libc6-dev)
SIMAVR_INCLUDE=/usr/include/simavr
EXIT_NO_TOOLCHAIN=3
EXIT_NO_SIMULATOR=4

log() { echo "[firmware] $*"; }

toolchain_present() {
    command -v avr-gcc >/dev/null && command -v avr-size >/dev/null \
        && [ -f "${ARDUINO_DIR}/Arduino.mk" ] \
        && [ -f "${ARDUINO_DIR}/hardware/arduino/avr/cores/arduino/Arduino.h" ] \
        && [ -f /usr/lib/avr/include/avr/io.h ]
}

simulator_present() {
    command -v cc >/dev/null && [ -f "${SIMAVR_INCLUDE}/sim_avr.h" ] \
        && [ -f "${SIMAVR_INCLUDE}/avr_uart.h" ] \
        && echo 'int main(void) { return 0; }' | cc -x c -o /dev/null - -lsimavr 2>/dev/null
}

# apt_install WHAT PACKAGE...
apt_install() {
    local what=$1
    shift
    if ! command -v apt-get >/dev/null; then
        log "no apt-get: install $* (or equivalents) by hand"
        return 1
    fi
    local sudo=()
    if [ "$(id -u)" != 0 ]; then
        # Only a password-less sudo: a prompt would hang `make test` and CI.
        if command -v sudo >/dev/null && sudo -n true 2>/dev/null; then
            sudo=(sudo -n)
        else
            log "not root and no password-less sudo: run 'sudo apt-get install $*' once"
            return 1
        fi
    fi
    log "installing ${what} with apt-get: $*"
    local start=${SECONDS}
    # Wait for a dpkg lock held by another install rather than fail on it.
    local apt=(env DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=300)
    if [ -z "${APT_UPDATED:-}" ]; then
        "${sudo[@]}" "${apt[@]}" update -qq || return 1
        APT_UPDATED=1
    fi
    # --no-install-recommends: the IDE that arduino-mk pulls in recommends a desktop's worth.
    "${sudo[@]}" "${apt[@]}" install -y -qq --no-install-recommends "$@" \
        >/dev/null || return 1
    log "apt-get took $((SECONDS - start)) s"
}

if toolchain_present; then
    log "toolchain present: $(avr-gcc --version | head -n 1)"
else
    if ! apt_install "the AVR toolchain" "${APT_PACKAGES[@]}" || ! toolchain_present; then
        log "TOOLCHAIN UNAVAILABLE: avr-gcc, avr-libc and ${ARDUINO_DIR}/Arduino.mk are needed"
        exit "${EXIT_NO_TOOLCHAIN}"
    fi
fi

log "compiling for the Arduino Mega 2560 (atmega2560) into ${BUILD_DIR}"
start=${SECONDS}
# A clean build each time: the check is "this source compiles", not "something once did".
make --no-print-directory -C "${FIRMWARE_DIR}" OBJDIR="${BUILD_DIR}" clean >/dev/null
mkdir -p "${BUILD_DIR}"
if ! make --no-print-directory -C "${FIRMWARE_DIR}" OBJDIR="${BUILD_DIR}" \
        >"${BUILD_DIR}/build.log" 2>&1; then
    cat "${BUILD_DIR}/build.log"
    log "FIRMWARE BUILD FAILED (log: ${BUILD_DIR}/build.log)"
    exit 1
fi
# Warnings are part of the check: -Wall -Wextra is on and any warning in our sources fails.
if grep -E "pma_firmware/[^:]+:[0-9]+:[0-9]+: warning" "${BUILD_DIR}/build.log"; then
    log "FIRMWARE BUILD HAS WARNINGS in our sources (log: ${BUILD_DIR}/build.log)"
    exit 1
fi
log "build took $((SECONDS - start)) s"

elf="${BUILD_DIR}/pma_firmware.elf"
[ -f "${elf}" ] || { log "no ${elf} after the build"; exit 1; }
# Berkeley format: text+data go to flash, data+bss are the static RAM.
read -r text data bss _ < <(avr-size -B "${elf}" | tail -n 1)
flash=$((text + data))
ram=$((data + bss))
flash_max=$((256 * 1024 - 8 * 1024))  # the stk500v2 bootloader keeps 8 KiB
ram_max=$((8 * 1024))
log "flash: ${flash} bytes of ${flash_max} ($((100 * flash / flash_max)) %)"
log "RAM:   ${ram} bytes of ${ram_max} static ($((100 * ram / ram_max)) %)," \
    "the rest is stack"
log "image: ${BUILD_DIR}/pma_firmware.hex"
if [ "${flash}" -gt "${flash_max}" ] || [ "${ram}" -gt $((ram_max * 3 / 4)) ]; then
    # Keep a quarter of the RAM for the stack: the Mega has no guard against a collision.
    log "FIRMWARE TOO LARGE for the atmega2560"
    exit 1
fi

# ---- The simulator that runs this image (firmware in the loop, docs/hardware.md).
if simulator_present; then
    log "simavr present: $(dpkg-query -W -f '${Version}' libsimavr-dev 2>/dev/null || echo '?')"
elif ! apt_install "simavr" "${SIMAVR_PACKAGES[@]}" || ! simulator_present; then
    log "SIMULATOR UNAVAILABLE: simavr's headers (${SIMAVR_INCLUDE}) and libsimavr are" \
        "needed for simavr_arduino; the firmware itself built"
    exit "${EXIT_NO_SIMULATOR}"
fi
if ! make --no-print-directory -C "${SIMAVR_DIR}" OUT="${BUILD_DIR}/simavr" \
        >"${BUILD_DIR}/simavr-build.log" 2>&1; then
    cat "${BUILD_DIR}/simavr-build.log"
    log "SIMULATOR BUILD FAILED (log: ${BUILD_DIR}/simavr-build.log)"
    exit 1
fi
log "simulator: ${BUILD_DIR}/simavr/pma_simavr (ros2 run pma_sim simavr_arduino)"

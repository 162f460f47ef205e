// Serial protocol v1 constants, device side (docs/serial-protocol.md). The host's twin is
// pma_common/pma_common/protocol.py; pma_driver/test/test_firmware_build.py reads both files
// and fails when they disagree, so change them together.
#pragma once

#include <avr/pgmspace.h>
#include <stdint.h>

const uint8_t PROTOCOL_VERSION = 1;
const char FIRMWARE_NAME[] PROGMEM = "pma_firmware";
const char FIRMWARE_VERSION[] PROGMEM = "0.1.2";
const uint32_t SERIAL_BAUD = 115200;
// One line either way, including '$', '*HH' and the line end.
const uint8_t MAX_LINE_BYTES = 96;

// Sample status bits (pma_interfaces/msg/PmaState STATUS_*).
const uint16_t STATUS_OVERPRESSURE = 1;
const uint16_t STATUS_HEARTBEAT_LOST = 2;
const uint16_t STATUS_ECHO_TIMEOUT = 4;
const uint16_t STATUS_SENSOR_RANGE = 8;

// Sample `valve` field (protocol.Valve).
const uint8_t VALVE_HOLD = 0;
const uint8_t VALVE_FILL = 1;
const uint8_t VALVE_VENT = 2;

// Device-to-host message types.
const char MESSAGE_HELLO[] PROGMEM = "HELLO";
const char MESSAGE_SAMPLE[] PROGMEM = "S";
const char MESSAGE_ACK[] PROGMEM = "ACK";
const char MESSAGE_NAK[] PROGMEM = "NAK";

// Host-to-device commands: COMMAND_<member of protocol.Command>.
const char COMMAND_HELLO[] PROGMEM = "HELLO";
const char COMMAND_HEARTBEAT[] PROGMEM = "HB";
const char COMMAND_SET[] PROGMEM = "SET";
const char COMMAND_VENT[] PROGMEM = "VENT";
const char COMMAND_RATE[] PROGMEM = "RATE";
const char COMMAND_TARE[] PROGMEM = "TARE";
const char COMMAND_HEARTBEAT_TIMEOUT[] PROGMEM = "HBTO";
const char COMMAND_MAX[] PROGMEM = "MAX";

// NAK reasons: NAK_<member of protocol.NakReason>.
const char NAK_RANGE[] PROGMEM = "RANGE";
const char NAK_SYNTAX[] PROGMEM = "SYNTAX";
const char NAK_UNKNOWN[] PROGMEM = "UNKNOWN";
const char NAK_CHECKSUM[] PROGMEM = "CHECKSUM";
// The command name of a NAK for a line whose name cannot be trusted (bad checksum or framing).
const char UNTRUSTED_COMMAND[] = "?";
// A NAK echoes at most this many characters of the command's name, so that the NAK of an
// unknown name as long as a whole line still fits in a line.
const uint8_t NAK_NAME_MAX = 12;

// Defaults reported in the HELLO banner and the limits of the commands that change them.
// 20 Hz leaves the HC-SR04 its ~38 ms no-echo cycle between pings. At 50 Hz a sample,
// echo timeout (6 ms) included, still fits in the 20 ms period.
const uint8_t DEFAULT_RATE_HZ = 20;
const uint8_t MAX_RATE_HZ = 50;
// The compiled pressure limit: the default ceiling and the most `MAX` may set. HELLO
// reports it as `limit_pa`, next to the current ceiling (`ceiling_pa`).
const int32_t CEILING_LIMIT_PA = 500000;
// A measured pressure above ceiling + this margin vents and latches OVERPRESSURE. Setpoints
// up to the ceiling itself are allowed, so at a setpoint equal to the ceiling the reading
// sits at the ceiling plus the regulation band (DEADBAND_PA, 5 kPa) plus sensor noise; a
// trip at the bare ceiling would fire there on every top step. 10 kPa is 2 % of the
// sensor's span, about 16 ADC counts.
const int32_t OVERPRESSURE_MARGIN_PA = 10000;
const uint16_t DEFAULT_HEARTBEAT_TIMEOUT_MS = 1000;
const uint16_t MIN_HEARTBEAT_TIMEOUT_MS = 100;
const uint16_t MAX_HEARTBEAT_TIMEOUT_MS = 10000;

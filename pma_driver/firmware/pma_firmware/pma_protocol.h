// Serial protocol v1 constants, device side (docs/serial-protocol.md). The host's twin is
// pma_driver/pma_driver/protocol.py; pma_driver/test/test_firmware_build.py reads both files
// and fails when they disagree, so change them together.
#pragma once

#include <avr/pgmspace.h>
#include <stdint.h>

const uint8_t PROTOCOL_VERSION = 1;
const char FIRMWARE_NAME[] PROGMEM = "pma_firmware";
const char FIRMWARE_VERSION[] PROGMEM = "0.1.0";
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

// Defaults reported in the HELLO banner and the limits of the commands that change them.
// 20 Hz leaves the HC-SR04 its ~38 ms no-echo cycle between pings. At 50 Hz an echo from up
// to 3 m fits in the period, but each echo timeout (30 ms) stretches it.
const uint8_t DEFAULT_RATE_HZ = 20;
const uint8_t MAX_RATE_HZ = 50;
// The compiled pressure limit: the default ceiling and the most `MAX` may set.
const int32_t CEILING_LIMIT_PA = 500000;
const uint16_t DEFAULT_HEARTBEAT_TIMEOUT_MS = 1000;
const uint16_t MIN_HEARTBEAT_TIMEOUT_MS = 100;
const uint16_t MAX_HEARTBEAT_TIMEOUT_MS = 10000;

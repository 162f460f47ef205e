// PMA testbed firmware for the Arduino Mega 2560.
//
// Reads the muscle's gauge pressure sensor and the HC-SR04 length sensor, streams samples to
// the host and holds the host's pressure setpoint with an inlet and an exhaust valve. It is
// the device side of docs/serial-protocol.md (protocol v1); the wiring is in docs/hardware.md.
//
// The device enforces its own safety whatever the host says or does: a ceiling on the
// setpoint and on the measured pressure (ceiling + OVERPRESSURE_MARGIN_PA), a heartbeat
// timeout that vents when the host link is lost, and venting when the pressure sensor reads
// outside its span. The simulated rig (pma_sim/pma_sim/device.py) follows the same rules.

#include <avr/interrupt.h>
#include <avr/sleep.h>

#include "pma_protocol.h"

// ---- Pins: docs/hardware.md has the same table (test_firmware_build.py compares them).
const uint8_t PIN_PRESSURE_SENSOR = A0;
const uint8_t PIN_ULTRASONIC_TRIGGER = 9;
const uint8_t PIN_ULTRASONIC_ECHO = 10;
const uint8_t PIN_INLET_VALVE = 5;
const uint8_t PIN_EXHAUST_VALVE = 6;
const uint8_t PIN_STATUS_LED = 13;

// The pin level that opens and the one that closes each valve. HIGH switches the MOSFET on,
// which opens a normally-closed valve. For a normally-open exhaust valve (docs/hardware.md
// recommends one: it vents when the power fails) swap the exhaust pair; for a driver board
// with active-low inputs swap both pairs.
const uint8_t INLET_OPEN_LEVEL = HIGH;
const uint8_t INLET_CLOSED_LEVEL = LOW;
const uint8_t EXHAUST_OPEN_LEVEL = HIGH;
const uint8_t EXHAUST_CLOSED_LEVEL = LOW;

// ---- Pressure sensor: the integer twin of calibration.PressureCalibration's defaults.
const int32_t ADC_REFERENCE_MV = 5000;  // AVcc: the sensor is ratiometric to the same 5 V
const int32_t ADC_FULL_SCALE = 1023;
const int32_t SENSOR_ZERO_MV = 500;
const int32_t SENSOR_FULL_MV = 4500;
const int32_t SENSOR_FULL_SCALE_PA = 500000;
const int32_t SENSOR_SPAN_MARGIN_MV = 100;  // calibration.adc_in_span's margin
const int32_t PA_PER_MV = SENSOR_FULL_SCALE_PA / (SENSOR_FULL_MV - SENSOR_ZERO_MV);
static_assert(PA_PER_MV * (SENSOR_FULL_MV - SENSOR_ZERO_MV) == SENSOR_FULL_SCALE_PA,
              "a whole number of Pa per mV keeps the conversion exact in 32 bits");
// Each reading is the rounded mean of a few conversions (~0.1 ms each), which keeps one noisy
// count from tripping the ceiling. There is no other filter.
const uint8_t ADC_OVERSAMPLING = 4;
// A zero offset beyond this is not sensor drift but air left in the muscle.
const int32_t TARE_MAX_OFFSET_PA = 25000;

// ---- Regulation.
// About 8 ADC counts: a narrower band makes the valves chatter on sensor noise.
const int32_t DEADBAND_PA = 5000;
// The valves are decided between samples too, so the pressure is held at 200 Hz.
const uint8_t REGULATION_PERIOD_MS = 5;

// ---- HC-SR04. pulseInLong() blocks until the echo ends or this timeout passes, and nothing
// else runs meanwhile (no regulation, no ceiling check), so it is only as long as the rig needs.
// The timeout runs from the call: it covers the ~0.45 ms the sensor takes to raise Echo
// and the echo itself, which leaves echoes up to ~5.5 ms, a target up to ~0.95 m away.
// The sensor sits within ~0.5 m of the plate; anything farther is no echo from it.
const uint32_t ECHO_TIMEOUT_US = 6000;
const uint8_t TRIGGER_PULSE_US = 10;

// ---- Idling. Between passes of loop() the CPU sleeps in idle mode (timers, UART and ADC run
// on) until the next interrupt, unless the next sample is due within this: a sleep ends at
// the latest on timer 0's next tick, 1.024 ms away, and the sample must not wait for it.
const int32_t IDLE_MARGIN_US = 1100;

// ---- State.
int32_t setpointPa = 0;
int32_t ceilingPa = CEILING_LIMIT_PA;
int32_t tareOffsetPa = 0;
uint8_t rateHz = DEFAULT_RATE_HZ;
uint32_t samplePeriodUs = 1000000UL / DEFAULT_RATE_HZ;
uint32_t nextSampleUs = 0;
uint32_t sampleSeq = 0;
uint16_t heartbeatTimeoutMs = DEFAULT_HEARTBEAT_TIMEOUT_MS;
uint32_t lastHeartbeatMs = 0;
uint32_t lastRegulationMs = 0;
// OVERPRESSURE and HEARTBEAT_LOST: they stay set until the host acknowledges them.
uint16_t latchedStatus = 0;
uint8_t valveState = VALVE_HOLD;
int16_t lastAdc = 0;
bool sensorInSpan = false;

char lineBuffer[MAX_LINE_BYTES];
uint8_t lineLength = 0;
bool discardingOverlongLine = false;

char frameBuffer[MAX_LINE_BYTES];
uint8_t frameLength = 0;
uint8_t frameChecksum = 0;

// ---- Pressure conversion.

int32_t divideRounded(int32_t numerator, int32_t denominator) {
  return (numerator >= 0 ? numerator + denominator / 2 : numerator - denominator / 2) /
         denominator;
}

// Gauge pressure before tare: (volts - 0.5 V) * 125 kPa/V, as millivolt * ADC counts.
int32_t untaredPressurePa(int16_t adc) {
  const int32_t scaledMv = (int32_t)adc * ADC_REFERENCE_MV - SENSOR_ZERO_MV * ADC_FULL_SCALE;
  return divideRounded(scaledMv * PA_PER_MV, ADC_FULL_SCALE);
}

bool adcInSensorSpan(int16_t adc) {
  const int32_t scaledMv = (int32_t)adc * ADC_REFERENCE_MV;
  return scaledMv >= (SENSOR_ZERO_MV - SENSOR_SPAN_MARGIN_MV) * ADC_FULL_SCALE &&
         scaledMv <= (SENSOR_FULL_MV + SENSOR_SPAN_MARGIN_MV) * ADC_FULL_SCALE;
}

int16_t readPressureAdc() {
  uint16_t sum = 0;
  for (uint8_t i = 0; i < ADC_OVERSAMPLING; ++i) {
    sum += analogRead(PIN_PRESSURE_SENSOR);
  }
  return (sum + ADC_OVERSAMPLING / 2) / ADC_OVERSAMPLING;
}

// ---- Valves.

void applyValves(uint8_t valve) {
  // Close before opening: both open at once would blow the supply straight to the exhaust.
  if (valve != VALVE_FILL) digitalWrite(PIN_INLET_VALVE, INLET_CLOSED_LEVEL);
  if (valve != VALVE_VENT) digitalWrite(PIN_EXHAUST_VALVE, EXHAUST_CLOSED_LEVEL);
  if (valve == VALVE_FILL) digitalWrite(PIN_INLET_VALVE, INLET_OPEN_LEVEL);
  if (valve == VALVE_VENT) digitalWrite(PIN_EXHAUST_VALVE, EXHAUST_OPEN_LEVEL);
  valveState = valve;
}

void tripOverpressure() {
  latchedStatus |= STATUS_OVERPRESSURE;
  setpointPa = 0;
}

// Measure, check the safety limits and decide the valves (bang-bang with a deadband).
void regulate() {
  lastAdc = readPressureAdc();
  sensorInSpan = adcInSensorSpan(lastAdc);
  const int32_t pressurePa = untaredPressurePa(lastAdc) - tareOffsetPa;
  // Checked even outside the span: a saturated sensor may well be a real overpressure. The
  // margin keeps regulation overshoot and noise at a setpoint equal to the ceiling from
  // tripping it (pma_protocol.h).
  if (pressurePa > ceilingPa + OVERPRESSURE_MARGIN_PA) tripOverpressure();

  uint8_t valve;
  if (!sensorInSpan || setpointPa == 0) {
    // Blind, or asked for nothing: an empty muscle is the safe state.
    valve = VALVE_VENT;
  } else if (pressurePa < setpointPa - DEADBAND_PA) {
    valve = VALVE_FILL;
  } else if (pressurePa > setpointPa + DEADBAND_PA) {
    valve = VALVE_VENT;
  } else {
    valve = VALVE_HOLD;
  }
  applyValves(valve);
  lastRegulationMs = millis();
}

// ---- HC-SR04.

// Echo pulse width in us, 0 when no echo came back within ECHO_TIMEOUT_US.
// pulseInLong times the edges with micros(), so an interrupt delays an edge by its own length
// at most. pulseIn counts turns of a loop instead, and every UART interrupt during the echo
// steals turns: with the host's commands arriving and their ACKs leaving it read up to ~100 us
// short, a muscle 17 mm too long (test_firmware_simavr.py measures both).
uint16_t measureEchoUs() {
  digitalWrite(PIN_ULTRASONIC_TRIGGER, LOW);
  delayMicroseconds(2);
  digitalWrite(PIN_ULTRASONIC_TRIGGER, HIGH);
  delayMicroseconds(TRIGGER_PULSE_US);
  digitalWrite(PIN_ULTRASONIC_TRIGGER, LOW);
  return (uint16_t)pulseInLong(PIN_ULTRASONIC_ECHO, HIGH, ECHO_TIMEOUT_US);
}

// ---- Frames out: `$body*HH\n`, the checksum kept while the body is written.

void appendChar(char c) {
  // Room for '*HH\n' stays reserved; our fields never come near it, so this only guards.
  if (frameLength < MAX_LINE_BYTES - 4) {
    frameBuffer[frameLength++] = c;
    frameChecksum ^= (uint8_t)c;
  }
}

void appendText(const char *text) {
  while (*text) appendChar(*text++);
}

void appendTextCut(const char *text, uint8_t maxLength) {
  for (; *text && maxLength > 0; --maxLength) appendChar(*text++);
}

void appendText_P(const char *flashText) {
  for (char c = pgm_read_byte(flashText); c; c = pgm_read_byte(++flashText)) appendChar(c);
}

void beginFrame(const char *flashType) {
  frameBuffer[0] = '$';
  frameLength = 1;
  frameChecksum = 0;
  appendText_P(flashType);
}

void addField(const char *text) {
  appendChar(',');
  appendText(text);
}

void addField_P(const char *flashText) {
  appendChar(',');
  appendText_P(flashText);
}

void addUnsigned(uint32_t value) {
  char digits[11];
  addField(ultoa(value, digits, 10));
}

void addSigned(int32_t value) {
  char digits[12];
  addField(ltoa(value, digits, 10));
}

void sendFrame() {
  static const char HEX_DIGITS[] = "0123456789ABCDEF";
  frameBuffer[frameLength++] = '*';
  frameBuffer[frameLength++] = HEX_DIGITS[frameChecksum >> 4];
  frameBuffer[frameLength++] = HEX_DIGITS[frameChecksum & 0x0F];
  frameBuffer[frameLength++] = '\n';
  Serial.write((const uint8_t *)frameBuffer, frameLength);
}

void sendHello() {
  beginFrame(MESSAGE_HELLO);
  addUnsigned(PROTOCOL_VERSION);
  addField_P(FIRMWARE_NAME);
  addField_P(FIRMWARE_VERSION);
  addUnsigned(rateHz);
  addUnsigned(MAX_RATE_HZ);
  addSigned(ceilingPa);
  addSigned(CEILING_LIMIT_PA);
  addUnsigned(heartbeatTimeoutMs);
  sendFrame();
}

void sendAck(const char *command) {
  beginFrame(MESSAGE_ACK);
  addField(command);
  sendFrame();
}

void sendAckValue(const char *command, int32_t value) {
  beginFrame(MESSAGE_ACK);
  addField(command);
  addSigned(value);
  sendFrame();
}

void sendNak(const char *command, const char *flashReason) {
  beginFrame(MESSAGE_NAK);
  appendChar(',');
  appendTextCut(command, NAK_NAME_MAX);
  addField_P(flashReason);
  sendFrame();
}

void sendSample() {
  const uint16_t echoUs = measureEchoUs();
  const uint32_t acquiredMs = millis();
  regulate();  // a fresh pressure reading and valve decision for this sample
  uint16_t status = latchedStatus;
  if (echoUs == 0) status |= STATUS_ECHO_TIMEOUT;
  if (!sensorInSpan) status |= STATUS_SENSOR_RANGE;

  beginFrame(MESSAGE_SAMPLE);
  addUnsigned(sampleSeq++);
  addUnsigned(acquiredMs);
  addUnsigned(lastAdc);
  addUnsigned(echoUs);
  addUnsigned(valveState);
  addSigned(setpointPa);
  addUnsigned(status);
  sendFrame();
}

// ---- Commands. Each handler gets the command's name (to echo) and its argument, if any.

void handleHello(const char *name, int32_t) {
  latchedStatus &= ~STATUS_HEARTBEAT_LOST;
  sendAck(name);
  sendHello();
}

void handleHeartbeat(const char *name, int32_t) {
  sendAck(name);
}

void handleSet(const char *name, int32_t pa) {
  if (pa < 0 || pa > ceilingPa) {
    sendNak(name, NAK_RANGE);
    return;
  }
  setpointPa = pa;
  // A new setpoint is the host's acknowledgement of the faults that vented the muscle.
  latchedStatus &= ~(STATUS_OVERPRESSURE | STATUS_HEARTBEAT_LOST);
  sendAckValue(name, pa);
}

void handleVent(const char *name, int32_t) {
  setpointPa = 0;
  regulate();  // open the exhaust now, not at the next regulation tick
  sendAck(name);
}

void handleRate(const char *name, int32_t hz) {
  if (hz < 1 || hz > MAX_RATE_HZ) {
    sendNak(name, NAK_RANGE);
    return;
  }
  rateHz = (uint8_t)hz;
  samplePeriodUs = 1000000UL / rateHz;
  nextSampleUs = micros() + samplePeriodUs;
  sendAckValue(name, hz);
}

void handleTare(const char *name, int32_t) {
  const int16_t adc = readPressureAdc();
  const int32_t offsetPa = untaredPressurePa(adc);
  if (!adcInSensorSpan(adc) || offsetPa > TARE_MAX_OFFSET_PA || offsetPa < -TARE_MAX_OFFSET_PA) {
    sendNak(name, NAK_RANGE);
    return;
  }
  tareOffsetPa = offsetPa;
  sendAckValue(name, adc);
}

void handleHeartbeatTimeout(const char *name, int32_t ms) {
  if (ms < MIN_HEARTBEAT_TIMEOUT_MS || ms > MAX_HEARTBEAT_TIMEOUT_MS) {
    sendNak(name, NAK_RANGE);
    return;
  }
  heartbeatTimeoutMs = (uint16_t)ms;
  sendAckValue(name, ms);
}

void handleMax(const char *name, int32_t pa) {
  if (pa < 1 || pa > CEILING_LIMIT_PA) {
    sendNak(name, NAK_RANGE);
    return;
  }
  ceilingPa = pa;
  if (setpointPa > ceilingPa) setpointPa = ceilingPa;
  sendAckValue(name, pa);
}

typedef void (*CommandHandler)(const char *name, int32_t argument);

struct CommandSpec {
  const char *name;  // in flash
  uint8_t argumentCount;
  CommandHandler handler;
};

// In flash: the table would otherwise cost RAM for the whole run.
const CommandSpec COMMANDS[] PROGMEM = {
    {COMMAND_HELLO, 0, handleHello},
    {COMMAND_HEARTBEAT, 0, handleHeartbeat},
    {COMMAND_SET, 1, handleSet},
    {COMMAND_VENT, 0, handleVent},
    {COMMAND_RATE, 1, handleRate},
    {COMMAND_TARE, 0, handleTare},
    {COMMAND_HEARTBEAT_TIMEOUT, 1, handleHeartbeatTimeout},
    {COMMAND_MAX, 1, handleMax},
};
const uint8_t COMMAND_COUNT = sizeof(COMMANDS) / sizeof(COMMANDS[0]);

int8_t hexDigitValue(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  return -1;
}

// Decimal integer with an optional '-'; values beyond 32 bits saturate (and fail the range
// checks) rather than wrap into an accepted value.
bool parseInteger(const char *text, int32_t *value) {
  const bool negative = *text == '-';
  if (negative) ++text;
  if (*text == '\0') return false;
  const uint32_t limit = negative ? 2147483648UL : 2147483647UL;
  uint32_t magnitude = 0;
  for (; *text; ++text) {
    if (*text < '0' || *text > '9') return false;
    const uint8_t digit = *text - '0';
    magnitude = magnitude > (limit - digit) / 10 ? limit : magnitude * 10 + digit;
  }
  *value = negative ? (int32_t)(0 - magnitude) : (int32_t)magnitude;
  return true;
}

// One complete line without its '\n'. Every command line gets exactly one ACK or NAK.
void handleLine(char *line, uint8_t length) {
  if (length > 0 && line[length - 1] == '\r') --length;
  // Overlong with its '\n' (the buffer also held a '\r'): dropped, as on the host.
  if (length + 1 > MAX_LINE_BYTES) return;
  // Noise or the partial line left in the USB buffer at port open: dropped, as on the host.
  if (length == 0 || line[0] != '$') return;
  if (length < 4 || line[length - 3] != '*') {
    sendNak(UNTRUSTED_COMMAND, NAK_SYNTAX);
    return;
  }
  const int8_t high = hexDigitValue(line[length - 2]);
  const int8_t low = hexDigitValue(line[length - 1]);
  if (high < 0 || low < 0) {
    sendNak(UNTRUSTED_COMMAND, NAK_SYNTAX);
    return;
  }
  uint8_t checksum = 0;
  for (uint8_t i = 1; i < length - 3; ++i) checksum ^= (uint8_t)line[i];
  if (checksum != (uint8_t)((high << 4) | low)) {
    sendNak(UNTRUSTED_COMMAND, NAK_CHECKSUM);
    return;
  }
  line[length - 3] = '\0';

  // Split the body in place: the name, at most one argument, and a count of the rest.
  char *name = line + 1;
  char *argument = nullptr;
  uint8_t fieldCount = 1;
  for (char *c = name; *c; ++c) {
    if (*c == ',') {
      *c = '\0';
      if (++fieldCount == 2) argument = c + 1;
    }
  }

  CommandSpec spec;
  uint8_t index = 0;
  for (; index < COMMAND_COUNT; ++index) {
    memcpy_P(&spec, &COMMANDS[index], sizeof(spec));
    if (strcmp_P(name, spec.name) == 0) break;
  }
  if (index == COMMAND_COUNT) {
    sendNak(name, NAK_UNKNOWN);
    return;
  }
  int32_t value = 0;
  if (fieldCount != spec.argumentCount + 1 ||
      (spec.argumentCount == 1 && !parseInteger(argument, &value))) {
    sendNak(name, NAK_SYNTAX);
    return;
  }
  // A well-formed command proves the host alive, even one refused for its value.
  lastHeartbeatMs = millis();
  spec.handler(name, value);
}

// Non-blocking: takes what has arrived and handles each line as its '\n' comes in.
void readCommands() {
  while (Serial.available() > 0) {
    const char c = (char)Serial.read();
    if (c == '\n') {
      if (!discardingOverlongLine) handleLine(lineBuffer, lineLength);
      lineLength = 0;
      discardingOverlongLine = false;
    } else if (discardingOverlongLine) {
      continue;
    } else if (lineLength < MAX_LINE_BYTES) {
      // Up to MAX_LINE_BYTES before the '\n': the one spare byte is a tolerated '\r'.
      lineBuffer[lineLength++] = c;
    } else {
      // No command is this long: drop it whole up to the next '\n'.
      discardingOverlongLine = true;
      lineLength = 0;
    }
  }
}

void checkHeartbeat() {
  if ((latchedStatus & STATUS_HEARTBEAT_LOST) == 0 &&
      millis() - lastHeartbeatMs >= heartbeatTimeoutMs) {
    // The host is gone or hung: nobody is watching the muscle, so empty it.
    latchedStatus |= STATUS_HEARTBEAT_LOST;
    setpointPa = 0;
    regulate();
  }
}

// Nothing is answered later for it: millis() moves only on timer 0's tick, which wakes the
// CPU, and a received byte wakes it at once. The board draws less, and a simulated board
// (simavr fast-forwards a sleep) costs the host a fraction of the CPU it took spinning.
void idleUntilNextInterrupt() {
  if ((int32_t)(nextSampleUs - micros()) <= IDLE_MARGIN_US) return;
  set_sleep_mode(SLEEP_MODE_IDLE);
  cli();
  if (Serial.available() == 0) {  // a byte that came after readCommands() is handled first
    sleep_enable();
    sei();  // the instruction after SEI runs before any interrupt: a wake-up cannot slip by
    sleep_cpu();
    sleep_disable();
  }
  sei();
}

void setup() {
  // Closed first, then outputs: the pins never drive a valve open during boot.
  digitalWrite(PIN_INLET_VALVE, INLET_CLOSED_LEVEL);
  digitalWrite(PIN_EXHAUST_VALVE, EXHAUST_CLOSED_LEVEL);
  pinMode(PIN_INLET_VALVE, OUTPUT);
  pinMode(PIN_EXHAUST_VALVE, OUTPUT);
  pinMode(PIN_ULTRASONIC_TRIGGER, OUTPUT);
  digitalWrite(PIN_ULTRASONIC_TRIGGER, LOW);
  pinMode(PIN_ULTRASONIC_ECHO, INPUT);
  pinMode(PIN_STATUS_LED, OUTPUT);
  analogReference(DEFAULT);

  Serial.begin(SERIAL_BAUD);
  lastHeartbeatMs = millis();
  nextSampleUs = micros() + samplePeriodUs;
  sendHello();
}

void loop() {
  readCommands();
  checkHeartbeat();

  const uint32_t nowUs = micros();
  if ((int32_t)(nowUs - nextSampleUs) >= 0) {
    // A steady schedule: the period does not stretch by the time a sample takes...
    nextSampleUs += samplePeriodUs;
    // ...but after a stall of a whole period (echo waits at 50 Hz) restart it instead of
    // sending a burst of back-to-back samples.
    if ((int32_t)(nowUs - nextSampleUs) >= 0) nextSampleUs = nowUs + samplePeriodUs;
    sendSample();
  } else if (millis() - lastRegulationMs >= REGULATION_PERIOD_MS) {
    regulate();
  }

  digitalWrite(PIN_STATUS_LED, (latchedStatus != 0 || !sensorInSpan) ? HIGH : LOW);
  idleUntilNextInterrupt();
}

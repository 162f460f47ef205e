// Host stand-in for the Arduino core: just the calls pma_firmware.ino makes, backed by a
// simulated rig (host_main.cpp) with a simulated clock, so the sketch's own source runs on
// the PC under test_firmware_build.py.
#pragma once

#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <avr/pgmspace.h>

const uint8_t LOW = 0;
const uint8_t HIGH = 1;
const uint8_t INPUT = 0;
const uint8_t OUTPUT = 1;
const uint8_t DEFAULT = 1;
const uint8_t A0 = 54;  // the Mega's first analog pin

uint32_t millis();
uint32_t micros();
void delayMicroseconds(unsigned int us);
void pinMode(uint8_t pin, uint8_t mode);
void digitalWrite(uint8_t pin, uint8_t level);
int analogRead(uint8_t pin);
void analogReference(uint8_t mode);
unsigned long pulseInLong(uint8_t pin, uint8_t state, unsigned long timeout_us);
char *ultoa(unsigned long value, char *buffer, int radix);
char *ltoa(long value, char *buffer, int radix);

class HostSerial {
 public:
  void begin(unsigned long baud);
  int available();
  int read();
  size_t write(const uint8_t *data, size_t length);
};

extern HostSerial Serial;

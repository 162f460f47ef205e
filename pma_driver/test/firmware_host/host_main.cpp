// A simulated rig around the unmodified firmware sketch, for test_firmware_build.py.
//
// Reads a script on stdin, one item a line:
//   !adc N       the pressure sensor's ADC count from now on
//   !echo N      the HC-SR04 echo width in us from now on (0 or too long: pulseInLong times out)
//   !run MS      run loop() for MS ms of simulated time
//   !loop_us N   simulated time one pass of loop() takes besides the sensor reads (default 40)
//   !pins        print "!pins <inlet> <exhaust>", 1 for an open valve (from the pins' levels)
//   anything else: sent to the firmware's serial input, with a '\n'
// and writes what the firmware sends, interleaved with the "!" lines it prints, on stdout.
// The clock starts at the microsecond count given as the first argument (default 0), so a
// test can start just before micros() wraps. Exits 2 if both valves are ever open at once.

#include <stdio.h>
#include <string>

#include "Arduino.h"

HostSerial Serial;

// The sketch itself, in this translation unit so its pin constants are in scope here.
#include "pma_firmware.ino"

namespace {

uint64_t nowUs = 0;
int adcCount = 0;
unsigned long echoUs = 0;
uint8_t pinLevels[70] = {0};
std::string serialInput;
size_t serialInputRead = 0;

// Real timings matter to the schedule: one conversion, one pass of loop()'s own code.
const uint64_t ADC_CONVERSION_US = 112;
uint64_t loopOverheadUs = 40;

}  // namespace

// Timer 0 overflows every 1024 us on the Mega (16 MHz, prescaler 64): it ends an idle sleep.
const uint64_t TIMER0_TICK_US = 1024;
void hostSleepUntilNextInterrupt() { nowUs = (nowUs / TIMER0_TICK_US + 1) * TIMER0_TICK_US; }

uint32_t millis() { return (uint32_t)(nowUs / 1000); }
uint32_t micros() { return (uint32_t)nowUs; }
void delayMicroseconds(unsigned int us) { nowUs += us; }
void pinMode(uint8_t, uint8_t) {}
void analogReference(uint8_t) {}

static bool inletOpen() { return pinLevels[PIN_INLET_VALVE] == INLET_OPEN_LEVEL; }
static bool exhaustOpen() { return pinLevels[PIN_EXHAUST_VALVE] == EXHAUST_OPEN_LEVEL; }

void digitalWrite(uint8_t pin, uint8_t level) {
  pinLevels[pin] = level;
  if (inletOpen() && exhaustOpen()) {
    fprintf(stdout, "!error both valves open at t=%llu us\n", (unsigned long long)nowUs);
    exit(2);
  }
}

int analogRead(uint8_t) {
  nowUs += ADC_CONVERSION_US;
  return adcCount;
}

// The HC-SR04 raises its echo line ~450 us after the trigger; pulseInLong's timeout runs from
// its call, so it covers that wait too (as in the Arduino core's wiring_pulse.c).
const unsigned long ECHO_START_US = 450;

unsigned long pulseInLong(uint8_t, uint8_t, unsigned long timeoutUs) {
  if (echoUs == 0 || ECHO_START_US + echoUs > timeoutUs) {
    nowUs += timeoutUs;
    return 0;
  }
  nowUs += ECHO_START_US + echoUs;
  return echoUs;
}

char *ultoa(unsigned long value, char *buffer, int) {
  sprintf(buffer, "%lu", value);
  return buffer;
}

char *ltoa(long value, char *buffer, int) {
  sprintf(buffer, "%ld", value);
  return buffer;
}

void HostSerial::begin(unsigned long) {}

int HostSerial::available() { return (int)(serialInput.size() - serialInputRead); }

int HostSerial::read() {
  if (serialInputRead >= serialInput.size()) return -1;
  return (uint8_t)serialInput[serialInputRead++];
}

size_t HostSerial::write(const uint8_t *data, size_t length) {
  fwrite(data, 1, length, stdout);
  return length;
}

int main(int argc, char **argv) {
  if (argc > 1) nowUs = strtoull(argv[1], nullptr, 10);
  setup();
  char line[4096];
  while (fgets(line, sizeof(line), stdin)) {
    std::string item(line);
    while (!item.empty() && item.back() == '\n') item.pop_back();
    if (item.rfind("!adc ", 0) == 0) {
      adcCount = atoi(item.c_str() + 5);
    } else if (item.rfind("!echo ", 0) == 0) {
      echoUs = strtoul(item.c_str() + 6, nullptr, 10);
    } else if (item.rfind("!loop_us ", 0) == 0) {
      loopOverheadUs = strtoull(item.c_str() + 9, nullptr, 10);
    } else if (item.rfind("!run ", 0) == 0) {
      const uint64_t end = nowUs + 1000ULL * strtoull(item.c_str() + 5, nullptr, 10);
      while (nowUs < end) {
        loop();
        nowUs += loopOverheadUs;
      }
    } else if (item == "!pins") {
      printf("!pins %d %d\n", inletOpen() ? 1 : 0, exhaustOpen() ? 1 : 0);
    } else {
      serialInput += item;
      serialInput += '\n';
    }
  }
  return 0;
}

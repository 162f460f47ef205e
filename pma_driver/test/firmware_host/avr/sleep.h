// Host stand-in for avr-libc's <avr/sleep.h>: an idle sleep lasts until the next interrupt,
// on the host the next tick of timer 0 (host_main.cpp), as serial input is there already.
#pragma once

#include <stdint.h>

const uint8_t SLEEP_MODE_IDLE = 0;

void hostSleepUntilNextInterrupt();

inline void set_sleep_mode(uint8_t) {}
inline void sleep_enable() {}
inline void sleep_disable() {}
inline void sleep_cpu() { hostSleepUntilNextInterrupt(); }

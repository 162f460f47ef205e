// Host stand-in for avr-libc's <avr/interrupt.h>: the host build has no interrupts to mask.
#pragma once

inline void cli() {}
inline void sei() {}

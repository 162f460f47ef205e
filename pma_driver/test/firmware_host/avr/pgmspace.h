// Host stand-in for avr-libc's <avr/pgmspace.h>: on a PC, flash is ordinary memory.
#pragma once

#include <stdint.h>
#include <string.h>

#define PROGMEM
#define pgm_read_byte(address) (*(const uint8_t *)(address))
#define memcpy_P memcpy
#define strcmp_P strcmp

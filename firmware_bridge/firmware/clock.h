/*
 * clock.h: the 64-bit MCU clock (Timer1 at 2 MHz plus a software overflow count) and the
 * 1 kHz wake-up tick (Timer2).
 *
 * Timer1 runs free in normal mode from clock_init() on and is never stopped, written or
 * reset: its compare unit A also times the trigger edges (trigger.c), so the clock and the
 * edges share one time base. clock_now() may be called with interrupts on or off, from the
 * main loop or an interrupt, and never masks them itself; it handles the overflow race (a
 * TCNT1 that wrapped while the overflow interrupt is still pending, or that wraps while the
 * overflow count is read). A bare TCNT1 reading is cheap enough to take per
 * received byte; clock_extend16() turns it back into a full tick as long as it is less
 * than 65536 ticks (32.8 ms) older than the `now` it is given.
 *
 * Timer2 only wakes the main loop from idle sleep once per millisecond, so time-outs (the
 * dead-man, the parser's inter-byte timeout) are checked at least that often.
 */
#ifndef CLOCK_H
#define CLOCK_H

#include <stdint.h>

void clock_init(void);

uint64_t clock_now(void);

/* The low 32 bits of clock_now(); call with interrupts disabled (an ISR). Cheaper. */
uint32_t clock_now32_isr(void);

uint64_t clock_extend16(uint16_t stamp, uint64_t now);

#endif /* CLOCK_H */

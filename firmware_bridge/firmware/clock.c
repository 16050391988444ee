/*
 * clock.c: Timer1 as a free-running 2 MHz counter extended to 64 bits; Timer2 as a 1 kHz
 * wake-up. See clock.h for the contract.
 *
 * Timer1: normal mode (WGM1 = 0), prescaler 8 (CS11). TCNT1 counts 0 ... 0xFFFF and the
 * overflow interrupt adds one to `overflows`; a tick is (overflows << 16) | TCNT1. Output
 * compare A belongs to trigger.c; compare B and input capture are unused.
 *
 * Timer2: CTC mode, prescaler 64, OCR2A = 249: an interrupt every 250 * 64 / 16 MHz = 1 ms
 * whose only job is to end the main loop's idle sleep.
 */
#include "clock.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#include "config.h"

static volatile uint32_t overflows;

void clock_init(void)
{
    TCCR1A = 0;
    TCCR1C = 0;
    TIFR1 = _BV(TOV1) | _BV(OCF1A) | _BV(OCF1B) | _BV(ICF1);
    TIMSK1 = _BV(TOIE1);
    TCCR1B = _BV(CS11);

    TCCR2A = _BV(WGM21);
    OCR2A = 249;
    TIFR2 = _BV(OCF2A);
    TIMSK2 = _BV(OCIE2A);
    TCCR2B = _BV(CS22);
}

ISR(TIMER1_OVF_vect)
{
    overflows++;
}

EMPTY_INTERRUPT(TIMER2_COMPA_vect)

/* The tick's bytes: avr-gcc turns a 64-bit shift into a bit-by-bit library loop, too slow
 * for the compare interrupt, so the parts are stored in place (the AVR is little-endian). */
typedef union {
    uint64_t tick;
    struct {
        uint16_t count;
        uint32_t overflows;
        uint16_t top;
    } parts;
} tick_parts_t;

static uint64_t now_masked(void)
{
    tick_parts_t now;
    now.parts.count = TCNT1;
    now.parts.overflows = overflows;
    /* TCNT1 wrapped but the overflow interrupt has not run yet: the flag is set and the
     * count is small. A large count with the flag set wrapped after it was read. */
    if ((TIFR1 & _BV(TOV1)) && now.parts.count < 0x8000u)
        now.parts.overflows++;
    now.parts.top = 0;
    return now.tick;
}

/* With interrupts on, a pending overflow interrupt runs at the next instruction boundary,
 * so a count read between two equal readings of `overflows` is consistent; interrupts are
 * masked only for the two-byte TCNT1 read (an interrupt touching another 16-bit Timer1
 * register in between would change the shared TEMP byte), not for the whole reading, so
 * the main loop holds off the encoder interrupt for a few cycles at most. */
static uint64_t now_unmasked(void)
{
    tick_parts_t now;
    uint32_t check;
    do {
        now.parts.overflows = overflows;
        cli();
        now.parts.count = TCNT1;
        sei();
        check = overflows;
    } while (check != now.parts.overflows);
    now.parts.top = 0;
    return now.tick;
}

uint64_t clock_now(void)
{
    return (SREG & _BV(SREG_I)) ? now_unmasked() : now_masked();
}

uint32_t clock_now32_isr(void)
{
    uint16_t count = TCNT1;
    uint16_t high = (uint16_t)overflows;
    if ((TIFR1 & _BV(TOV1)) && count < 0x8000u)
        high++;
    return ((uint32_t)high << 16) | count;
}

uint64_t clock_extend16(uint16_t stamp, uint64_t now)
{
    uint16_t age = (uint16_t)((uint16_t)now - stamp);
    return now - age;
}

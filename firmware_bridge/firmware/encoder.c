/*
 * encoder.c: x4 quadrature decoding in the INT0 / INT1 interrupts (see encoder.h).
 *
 * The state is (A << 1) | B; STEP[(previous << 2) | current] is +1, -1 or 0.
 */
#include "encoder.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/pgmspace.h>

#include "trigger.h"

static const int8_t STEP[16] PROGMEM = {
    0, -1, +1, 0,
    +1, 0, 0, -1,
    -1, 0, 0, +1,
    0, +1, -1, 0,
};

static volatile int32_t position;
static uint8_t previous;

static uint8_t read_state(void)
{
    uint8_t pins = PIND;
    return (uint8_t)(((pins >> PD2) & 1u) << 1 | ((pins >> PD3) & 1u));
}

void encoder_init(void)
{
    DDRD &= ~(_BV(PD2) | _BV(PD3));
    previous = read_state();
    EICRA = _BV(ISC00) | _BV(ISC10);
    EIFR = _BV(INTF0) | _BV(INTF1);
    EIMSK = _BV(INT0) | _BV(INT1);
}

ISR(INT0_vect)
{
    uint8_t current = read_state();
    int8_t step = (int8_t)pgm_read_byte(&STEP[(previous << 2) | current]);
    previous = current;
    if (step) {
        int32_t now = position + step;
        position = now;
        trigger_encoder_moved(now);
    }
}

ISR(INT1_vect, ISR_ALIASOF(INT0_vect));

int32_t encoder_position(void)
{
    uint8_t sreg = SREG;
    cli();
    int32_t value = position;
    SREG = sreg;
    return value;
}

int32_t encoder_position_isr(void)
{
    return position;
}

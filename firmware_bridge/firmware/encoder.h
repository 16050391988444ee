/*
 * encoder.h: quadrature encoder on INT0 (PD2, channel A) and INT1 (PD3, channel B), x4.
 *
 * Both external interrupts fire on any change; each reads both channels and steps the
 * 32-bit position by the Gray-code transition: A leading B (A, B = 00, 10, 11, 01, 00) counts
 * up. A transition that skips a state (both channels changed between two interrupts, i.e.
 * the encoder outran the interrupt) is ignored and not counted. The position starts at 0 at
 * reset and is never reset by the protocol. After each count the trigger engine is told.
 */
#ifndef ENCODER_H
#define ENCODER_H

#include <stdint.h>

void encoder_init(void);

/* The position; safe from any context. */
int32_t encoder_position(void);

/* The position without masking interrupts: only from an interrupt. */
int32_t encoder_position_isr(void);

#endif /* ENCODER_H */

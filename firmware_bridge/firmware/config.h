/*
 * config.h: the trigger firmware's fixed choices: clock, pins, baud rate, limits.
 *
 * Target: ATmega328P at 16 MHz (an Arduino Uno or Nano board). Everything the host can
 * change goes over the protocol (firmware_bridge/messages.py); everything here is fixed at
 * build time and documented in README.md beside this file.
 *
 *   PB1 / OC1A (Arduino D9)  camera trigger output, driven by Timer1's output compare unit
 *   PD2 / INT0 (Arduino D2)  encoder channel A (input, no internal pull-up)
 *   PD3 / INT1 (Arduino D3)  encoder channel B (input, no internal pull-up)
 *   PD0 / PD1                UART0 RX / TX, 500000 baud 8N1 (U2X, UBRR0 = 3, exact at 16 MHz)
 *   PC0 (Arduino A0)         only in the test build (TRIGGER_TEST_HOOKS): pulled up; low
 *                            hangs the main loop so the watchdog can be seen to reset it
 *
 * Time: one tick is one count of Timer1 at F_CPU / 8 = 2 MHz (500 ns), extended to 64 bits
 * by counting overflows (clock.c). Every time on the wire is in ticks.
 */
#ifndef CONFIG_H
#define CONFIG_H

#ifndef F_CPU
#define F_CPU 16000000UL
#endif

#define TICK_HZ (F_CPU / 8UL)

#define UART_BAUD 500000UL
#define UART_UBRR ((F_CPU / (8UL * UART_BAUD)) - 1UL)

/* Shortest pulse and shortest gap between pulses: the compare interrupt that programs the
 * next edge must have run before that edge is due, including the time other interrupts may
 * hold it off. 100 ticks = 50 us. Longest pulse and period: 2^31 ticks (17.9 min). */
#define MIN_INTERVAL_TICKS 100UL
#define MAX_INTERVAL_TICKS 0x80000000UL

/* How far ahead of "now" an edge is programmed when it is wanted as soon as possible:
 * ARM with start_tick 0, and an encoder position that reached the divisor. */
#define ARM_LEAD_TICKS 400UL
#define ENCODER_LEAD_TICKS 32UL

/* A packet whose bytes stop arriving for this long is dropped (10 ms). */
#define INTERBYTE_TIMEOUT_TICKS (TICK_HZ / 100UL)

/* Ring sizes: powers of two. RX entries carry a 16-bit receive stamp (TCNT1). */
#define RX_RING_SIZE 128
#define TX_RING_SIZE 256
#define EVENT_QUEUE_SIZE 8

#endif /* CONFIG_H */

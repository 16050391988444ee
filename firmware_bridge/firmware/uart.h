/*
 * uart.h: UART0 with interrupt-driven receive and transmit rings.
 *
 * Receive: the RX-complete interrupt stores each byte with TCNT1 read in that interrupt
 * (a 16-bit stamp, clock_extend16() in clock.h makes it a tick), so a packet's reception
 * time is the time its last byte came in, not the time the main loop got round to it.
 *
 * Both UART interrupts are nestable: they mask their own enable bit and re-enable
 * interrupts within about 20 cycles, so the encoder and trigger interrupts are not held
 * off for the whole handler (uart.c). A stamp is therefore a few microseconds after the
 * stop bit, or up to about 20 us when a trigger interrupt ran first. The
 * main loop takes bytes out within a few milliseconds (the stamp is good for 32.8 ms). A
 * byte that finds the ring full is dropped; the parser's resync turns the damage into ERROR
 * packets, never a stuck stream.
 *
 * Transmit: uart_write() copies into the ring and enables the data-register-empty interrupt;
 * it never waits. Callers ask uart_tx_free() first and write whole packets only, so a packet
 * is never cut; nothing here blocks the trigger timing.
 */
#ifndef UART_H
#define UART_H

#include <stdint.h>

void uart_init(void);

/* Next received byte and its stamp; returns 0 when the ring is empty. */
uint8_t uart_read(uint8_t *byte, uint16_t *stamp);

uint8_t uart_rx_pending(void);

uint16_t uart_tx_free(void);

/* Append `length` bytes; the caller has checked uart_tx_free(). */
void uart_write(const uint8_t *data, uint8_t length);

#endif /* UART_H */

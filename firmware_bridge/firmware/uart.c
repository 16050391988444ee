/*
 * uart.c: UART0 at UART_BAUD (config.h), 8 data bits, no parity, one stop bit, double speed
 * (U2X0). Single producer / single consumer rings: the interrupt owns one index of each,
 * the main loop the other, so neither side needs more than an 8-bit atomic read.
 */
#include "uart.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#include "config.h"

#define RX_MASK (RX_RING_SIZE - 1)
#define TX_MASK (TX_RING_SIZE - 1)

static volatile uint8_t rx_byte[RX_RING_SIZE];
static volatile uint16_t rx_stamp[RX_RING_SIZE];
static volatile uint8_t rx_head;
static volatile uint8_t rx_tail;

static volatile uint8_t tx_ring[TX_RING_SIZE];
static volatile uint8_t tx_head;
static volatile uint8_t tx_tail;

/* U2X0 before the baud rate: simavr works out its byte time when UBRR0L is written. */
void uart_init(void)
{
    UCSR0A = _BV(U2X0);
    UBRR0H = (uint8_t)(UART_UBRR >> 8);
    UBRR0L = (uint8_t)UART_UBRR;
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

/*
 * The two UART vectors let the encoder (and trigger) interrupts in as early as possible: a
 * naked stub clears the vector's own enable bit in UCSR0B (so it cannot re-enter while its
 * flag is still set), re-enables interrupts and jumps to the handler, a `signal` function
 * (it saves what it uses and returns with reti), which sets the enable bit again at its
 * end with interrupts masked. About 20 cycles pass with interrupts masked instead of the
 * whole handler. Nothing the nested interrupts do touches the rings or UCSR0B.
 */
#pragma GCC diagnostic ignored "-Wmisspelled-isr"
void uart_rx_handler(void) __attribute__((signal, used, externally_visible));
void uart_tx_handler(void) __attribute__((signal, used, externally_visible));

#define DEFERRED_VECTOR(vector, handler, enable_bit)                                            \
    ISR(vector, ISR_NAKED)                                                                      \
    {                                                                                           \
        asm volatile("push r24\n\t"                                                             \
                     "in r24, __SREG__\n\t"                                                     \
                     "push r24\n\t"                                                             \
                     "lds r24, %[ucsrb]\n\t"                                                    \
                     "andi r24, %[mask]\n\t"                                                    \
                     "sts %[ucsrb], r24\n\t"                                                    \
                     "pop r24\n\t"                                                              \
                     "out __SREG__, r24\n\t"                                                    \
                     "pop r24\n\t"                                                              \
                     "sei\n\t"                                                                  \
                     "jmp " #handler "\n\t"                                                     \
                     ::[ucsrb] "n"(_SFR_MEM_ADDR(UCSR0B)),                                      \
                     [mask] "n"(0xFF & ~_BV(enable_bit)));                                      \
    }

DEFERRED_VECTOR(USART_RX_vect, uart_rx_handler, RXCIE0)
DEFERRED_VECTOR(USART_UDRE_vect, uart_tx_handler, UDRIE0)

/* The stamp is TCNT1 alone, read with interrupts masked (two bytes through Timer1's shared
 * TEMP register), extended to a full tick by the main loop (clock_extend16). */
void uart_rx_handler(void)
{
    cli();
    uint8_t byte = UDR0;
    uint16_t stamp = TCNT1;
    sei();
    uint8_t head = rx_head;
    uint8_t next = (head + 1) & RX_MASK;
    if (next != rx_tail) {
        rx_byte[head] = byte;
        rx_stamp[head] = stamp;
        rx_head = next;
    }
    cli();
    UCSR0B |= _BV(RXCIE0);
}

void uart_tx_handler(void)
{
    uint8_t tail = tx_tail;
    if (tail == tx_head)
        return;
    UDR0 = tx_ring[tail];
    tx_tail = (uint8_t)((tail + 1) & TX_MASK);
    cli();
    UCSR0B |= _BV(UDRIE0);
}

uint8_t uart_read(uint8_t *byte, uint16_t *stamp)
{
    uint8_t tail = rx_tail;
    if (tail == rx_head)
        return 0;
    *byte = rx_byte[tail];
    *stamp = rx_stamp[tail];
    rx_tail = (tail + 1) & RX_MASK;
    return 1;
}

uint8_t uart_rx_pending(void)
{
    return rx_tail != rx_head;
}

uint16_t uart_tx_free(void)
{
    uint8_t used = (uint8_t)((tx_head - tx_tail) & TX_MASK);
    return (uint16_t)(TX_RING_SIZE - 1 - used);
}

void uart_write(const uint8_t *data, uint8_t length)
{
    uint8_t head = tx_head;
    for (uint8_t i = 0; i < length; i++) {
        tx_ring[head] = data[i];
        head = (uint8_t)((head + 1) & TX_MASK);
    }
    tx_head = head;
    UCSR0B |= _BV(UDRIE0);
}

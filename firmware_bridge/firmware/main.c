/*
 * main.c: the trigger microcontroller's firmware: reset cause, start-up, main loop.
 *
 * What this firmware is: the hard-real-time half of the appliance's camera triggering
 * (the Klipper split). The host schedules in MCU ticks; the firmware makes the edges with
 * Timer1's compare hardware, counts the crosshead encoder, timestamps every trigger and
 * reports it, and stops on its own when the host goes quiet (dead-man). Modules:
 *   clock.c     64-bit tick (Timer1 at 2 MHz), 1 kHz wake-up (Timer2)
 *   uart.c      UART0 rings, per-byte receive stamps
 *   protocol.c  packet parser, commands, replies, dead-man
 *   trigger.c   pulse engine on OC1A (period or encoder mode)
 *   encoder.c   x4 quadrature on INT0 / INT1
 * The message table is messages.h, generated from firmware_bridge/messages.py.
 *
 * Reset cause: MCUSR is read and cleared in .init3, before anything else runs, and the
 * watchdog is switched off there (after a watchdog reset it stays on with its shortest
 * time-out). Priority when several flags are set: watchdog, power-on, brown-out, external.
 * With a bootloader that clears MCUSR itself (Arduino's optiboot) the cause reads OTHER.
 *
 * Watchdog: 120 ms (WDTO_120MS), reset once per main-loop pass. The main loop never waits
 * for anything: it sleeps in idle mode when there is nothing to do and any interrupt (at
 * least the 1 kHz Timer2 one) wakes it, so a pass takes well under a millisecond unless
 * the firmware is stuck; then the watchdog resets it and BOOT(WATCHDOG) is sent. The check
 * before sleeping does not mask interrupts (that would hold off the encoder interrupt): work
 * that an interrupt queues just after the check waits for the next wake-up, at most 1 ms.
 *
 * Not here: no EEPROM settings (everything comes from the host after each reset), no
 * brown-out configuration (fuses), no bootloader.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>

#include "clock.h"
#include "encoder.h"
#include "messages.h"
#include "protocol.h"
#include "test_hooks.h"
#include "trigger.h"
#include "uart.h"

uint8_t reset_flags __attribute__((section(".noinit")));

void read_reset_flags(void) __attribute__((naked, used, section(".init3")));
void read_reset_flags(void)
{
    reset_flags = MCUSR;
    MCUSR = 0;
    wdt_disable();
}

static uint8_t reset_cause(uint8_t flags)
{
    if (flags & _BV(WDRF))
        return RESET_CAUSE_WATCHDOG;
    if (flags & _BV(PORF))
        return RESET_CAUSE_POWER_ON;
    if (flags & _BV(BORF))
        return RESET_CAUSE_BROWN_OUT;
    if (flags & _BV(EXTRF))
        return RESET_CAUSE_EXTERNAL;
    return RESET_CAUSE_OTHER;
}

int main(void)
{
    wdt_enable(WDTO_120MS);
    clock_init();
    uart_init();
    trigger_init();
    encoder_init();
    test_hooks_init();
    set_sleep_mode(SLEEP_MODE_IDLE);
    sei();
    protocol_send_boot(reset_cause(reset_flags));
    for (;;) {
        wdt_reset();
        test_hooks_poll();
        protocol_poll();
        if (!protocol_busy()) {
            sleep_enable();
            sleep_cpu();
            sleep_disable();
        }
    }
}

/*
 * test_hooks.c: the test build's "hang the main loop" pin (see test_hooks.h). Empty unless
 * TRIGGER_TEST_HOOKS is defined.
 */
#include "test_hooks.h"

#ifdef TRIGGER_TEST_HOOKS

#include <avr/io.h>

void test_hooks_init(void)
{
    DDRC &= ~_BV(PC0);
    PORTC |= _BV(PC0);
}

void test_hooks_poll(void)
{
    if (!(PINC & _BV(PC0)))
        for (;;) {
        }
}

#endif

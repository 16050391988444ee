/*
 * test_hooks.h: a fault the tests can provoke, compiled in only for the test build.
 *
 * With TRIGGER_TEST_HOOKS defined (firmware_build.build_firmware(..., test_hooks=True)
 * builds trigger-test.elf), PC0 is an input with its pull-up on, and test_hooks_poll()
 * stops the main loop for good when it reads low (interrupts keep running, the watchdog is
 * no longer reset), so a test can see the watchdog reset the firmware and BOOT(WATCHDOG)
 * come out. After that reset the pull-up is switched on again (simavr's pull-up then wins
 * over the harness's drive, as a weak driver would lose on hardware) and the firmware runs
 * normally. The production build has no such pin function: test_hooks_init() and
 * test_hooks_poll() are empty and the ELF contains none of it.
 */
#ifndef TEST_HOOKS_H
#define TEST_HOOKS_H

#ifdef TRIGGER_TEST_HOOKS
void test_hooks_init(void);
void test_hooks_poll(void);
#else
static inline void test_hooks_init(void) {}
static inline void test_hooks_poll(void) {}
#endif

#endif /* TEST_HOOKS_H */

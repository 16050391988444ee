/*
 * trigger.h: the camera trigger engine on PB1 / OC1A.
 *
 * Every pin edge is made by Timer1's output compare unit in toggle mode, so an edge happens
 * on the exact timer tick it was programmed for, whatever the CPU is doing; the compare
 * interrupt only programs the next edge. Edges more than a timer wrap (32.8 ms) away are
 * reached by "hops": the output is disconnected and the compare fires every 16.4 ms until
 * the edge is within reach, then it is connected for the one match that makes the edge.
 *
 * Period mode: the first pulse rises at start_tick (or ARM + ARM_LEAD_TICKS when 0), the
 * next ones every period_ticks after it, each pulse_width_ticks long.
 *
 * Encoder mode: the first pulse rises at start_tick like in period mode and records the
 * encoder position. After that a pulse starts ENCODER_LEAD_TICKS after the encoder
 * interrupt in which |position - position of the last trigger| reached encoder_divisor; the
 * last trigger position then moves by exactly the divisor, so triggers stay on multiples of
 * the divisor from the first one. Reverse motion triggers the same way (positions then go
 * down by the divisor); a reversal just after a trigger needs the full divisor back. If the
 * divisor is reached again while a pulse (or the minimum gap after it) is still running, one
 * pulse follows as soon as allowed; reaching it twice in that time skips a pulse (the
 * TRIGGER positions show the gap). The tick in TRIGGER is always the rising edge's tick.
 *
 * Re-timing (trigger_retime, while armed): the spacing changes without a stop, so the pulse
 * width, the count and trigger_seq carry on. Period mode: the falling edge's interrupt
 * programs the next rise at rise + period_ticks, so the new period first separates pulse k
 * from pulse k + 1, k being the first pulse whose falling edge (its compare interrupt, a few
 * us after the edge) comes after the change; a rise that is already programmed keeps its
 * tick. Encoder mode: the next pulse is due when |position - last trigger position| reaches
 * the new divisor, and the grid goes on in steps of it from there. When the encoder is
 * already that far or further from the last trigger position, the last trigger position is
 * moved to one count less than the new divisor behind the position (in the direction it
 * moved), so the next count triggers once instead of a burst catching up the grid. A pulse
 * already due (the divisor reached while a pulse ran) still follows.
 *
 * count > 0 stops after that many pulses (STOPPED COUNT_DONE); a stop request (DISARM,
 * dead-man) while a pulse is high lets that pulse end at its width first. TRIGGER events
 * and the one STOPPED are queued here and sent by the main loop (protocol.c); an event
 * that finds the queue full is lost and shows as a gap in trigger_seq.
 *
 * Encoder-mode timing carries the encoder interrupt's latency (about 28.5 us from the count,
 * constant but for the cycles another interrupt holds it off: the UART handlers' masked
 * preamble, the timer overflow, or a trigger compare interrupt that is running).
 *
 * Not done: trigger output polarity is fixed (active high); no minimum is enforced between
 * encoder pulses beyond MIN_INTERVAL_TICKS.
 */
#ifndef TRIGGER_H
#define TRIGGER_H

#include <stdint.h>

#include "messages.h"

void trigger_init(void);

/* 0, or the ERROR_CODE_* that rejects the configuration. */
uint8_t trigger_configure(const msg_configure_t *config);

/* 0, or the ERROR_CODE_* that refuses the new spacing: BAD_STATE unless armed, BAD_VALUE for
 * a period (PERIOD source; the configured pulse width must fit) or divisor (ENCODER) that
 * CONFIGURE would refuse; the field of the other source is ignored. Accepted, it changes the
 * running trigger and the stored configuration with interrupts masked. */
uint8_t trigger_retime(const msg_retime_t *retime);

/* 0, or the ERROR_CODE_* that refuses to arm; `now` is the current tick. */
uint8_t trigger_arm(uint64_t now);

/* Ask triggering to stop with a STOP_REASON_*; nothing happens when disarmed. */
void trigger_stop(uint8_t reason);

uint8_t trigger_is_armed(void);

/* Called by the encoder interrupt after every count. */
void trigger_encoder_moved(int32_t position);

/* Output waiting to be sent: TRIGGER events first, then STOPPED. */
uint8_t trigger_output_pending(void);
uint8_t trigger_peek_event(msg_trigger_t *event);
void trigger_drop_event(void);
uint8_t trigger_peek_stopped(msg_stopped_t *stopped);
void trigger_drop_stopped(void);

#endif /* TRIGGER_H */

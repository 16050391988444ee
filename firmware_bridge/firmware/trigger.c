/*
 * trigger.c: the trigger engine (see trigger.h for what it does).
 *
 * Phases of the compare unit while armed:
 *   PHASE_HOP       output disconnected, OCR1A at an intermediate tick; the next edge is
 *                   more than HOP_REACH ticks away
 *   PHASE_EDGE      output connected in toggle mode, OCR1A one tick before `edge_tick`
 *                   (the pin changes when TCNT1 leaves the compare value, i.e. at the start
 *                   of tick OCR1A + 1), so the edge is exactly at `edge_tick`
 *   PHASE_ENC_WAIT  encoder mode, between pulses: output disconnected and low, compare
 *                   interrupt off, waiting for trigger_encoder_moved()
 * While disconnected, PORTB1 holds the output's current level, so the pin does not change
 * when the compare unit lets go of it.
 *
 * TIFR1 is never written here: simavr 1.6 drops a pending Timer1 overflow when OCF1A is
 * cleared by writing TIFR1 (the 64-bit clock then loses 32.8 ms). A compare flag left over
 * from while the interrupt was off is recognised instead: the interrupt then finds the
 * programmed edge still in the future and ignores itself.
 *
 * The state below is changed only with interrupts disabled: in the compare and encoder
 * interrupts, or in trigger_arm(), trigger_stop() and trigger_retime(), which mask
 * interrupts around their work. trigger_configure() writes the configuration only while
 * disarmed, when no interrupt reads it; the output queue has one producer and one consumer
 * (see trigger_peek_event).
 */
#include "trigger.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <string.h>

#include "clock.h"
#include "config.h"
#include "encoder.h"

#define PHASE_IDLE 0
#define PHASE_HOP 1
#define PHASE_EDGE 2
#define PHASE_ENC_WAIT 3

#define NO_STOP 0xFF

/* An edge is programmed directly only when at most this far ahead: no earlier alias of
 * the 16-bit compare value lies in between, and the interrupt has margin on both sides. */
#define HOP_REACH 49152L
#define HOP_STEP 32768U
/* A start further away than this is hopped towards with 64-bit arithmetic; everything
 * nearer (and every pulse width and period, limited to 2^31 ticks) takes the 32-bit path. */
#define FAR_TICKS (1L << 30)
/* Closest an edge may be programmed to the clock reading in program_edge(): covers the
 * cycles from reading TCNT1 to writing OCR1A (about 100, or 130 on the late path; a tick
 * is 8 cycles) with margin. */
#define MIN_AHEAD_TICKS 32L

static msg_configure_t config;
static uint8_t configured;

static volatile uint8_t armed;
static uint8_t phase;
static uint8_t level;
static uint8_t stop_reason;
static uint64_t edge_tick;
static uint64_t rise_tick;
static uint32_t triggers;

static uint8_t encoder_started;
static uint8_t encoder_pending;
static int32_t last_trigger_position;
static int32_t pulse_position;
static int32_t pending_position;

static msg_trigger_t events[EVENT_QUEUE_SIZE];
static volatile uint8_t event_head;
static volatile uint8_t event_tail;

static msg_stopped_t stopped;
static volatile uint8_t stopped_pending;

static void output_connect(void)
{
    TCCR1A = _BV(COM1A0);
}

static void output_disconnect(void)
{
    if (level)
        PORTB |= _BV(PB1);
    else
        PORTB &= ~_BV(PB1);
    TCCR1A = 0;
}

/* Program the compare unit for an edge at `tick`, which must be less than 2^31 ticks
 * from now: directly when within HOP_REACH, else by hops. An edge that is already too
 * close (a late interrupt) is moved to the earliest safe tick. This is the fast path of
 * the compare and encoder interrupts, hence 32-bit arithmetic only. */
static void program_edge(uint64_t tick)
{
    uint32_t compare = (uint32_t)tick - 1;
    uint32_t now = clock_now32_isr();
    int32_t ahead = (int32_t)(compare - now);
    edge_tick = tick;
    if (ahead < MIN_AHEAD_TICKS) {
        compare = now + MIN_AHEAD_TICKS;
        edge_tick += (uint32_t)(MIN_AHEAD_TICKS - ahead);
        ahead = MIN_AHEAD_TICKS;
    }
    if (ahead <= HOP_REACH) {
        OCR1A = (uint16_t)compare;
        output_connect();
        phase = PHASE_EDGE;
    } else {
        OCR1A = (uint16_t)(now + HOP_STEP);
        output_disconnect();
        phase = PHASE_HOP;
    }
    TIMSK1 |= _BV(OCIE1A);
}

/* Any edge, however far: hops with 64-bit arithmetic until it is nearer than FAR_TICKS. */
static void schedule_edge(uint64_t tick)
{
    uint64_t now = clock_now();
    if (tick > now + FAR_TICKS) {
        edge_tick = tick;
        OCR1A = (uint16_t)(now + HOP_STEP);
        output_disconnect();
        phase = PHASE_HOP;
        TIMSK1 |= _BV(OCIE1A);
    } else {
        program_edge(tick);
    }
}

static void finish(uint8_t reason)
{
    TIMSK1 &= ~_BV(OCIE1A);
    level = 0;
    output_disconnect();
    phase = PHASE_IDLE;
    armed = 0;
    stopped.reason = reason;
    stopped.triggers = triggers;
    stopped_pending = 1;
}

static void push_event(uint64_t tick, int32_t position)
{
    uint8_t head = event_head;
    uint8_t next = (uint8_t)((head + 1) % EVENT_QUEUE_SIZE);
    if (next == event_tail)
        return;
    events[head].trigger_seq = triggers;
    events[head].tick = tick;
    events[head].position = position;
    event_head = next;
}

static void on_rise(void)
{
    rise_tick = edge_tick;
    triggers++;
    int32_t position;
    if (config.source == TRIGGER_SOURCE_ENCODER) {
        if (!encoder_started) {
            pulse_position = encoder_position_isr();
            last_trigger_position = pulse_position;
            encoder_started = 1;
        }
        position = pulse_position;
    } else {
        position = encoder_position_isr();
    }
    push_event(rise_tick, position);
    program_edge(rise_tick + config.pulse_width_ticks);
}

/* Start an encoder pulse ENCODER_LEAD_TICKS from now, from a single clock reading (the
 * encoder interrupt's latency is the trigger's). */
static void start_encoder_pulse_now(void)
{
    uint64_t now = clock_now();
    level = 0;
    edge_tick = now + ENCODER_LEAD_TICKS;
    OCR1A = (uint16_t)((uint16_t)now + (ENCODER_LEAD_TICKS - 1));
    output_connect();
    phase = PHASE_EDGE;
    TIMSK1 |= _BV(OCIE1A);
}

static void on_fall(void)
{
    if (stop_reason != NO_STOP) {
        finish(stop_reason);
        return;
    }
    if (config.count && triggers >= config.count) {
        finish(STOP_REASON_COUNT_DONE);
        return;
    }
    if (config.source == TRIGGER_SOURCE_PERIOD) {
        program_edge(rise_tick + config.period_ticks);
        return;
    }
    if (encoder_pending) {
        encoder_pending = 0;
        pulse_position = pending_position;
        program_edge(edge_tick + MIN_INTERVAL_TICKS);
        return;
    }
    TIMSK1 &= ~_BV(OCIE1A);
    output_disconnect();
    phase = PHASE_ENC_WAIT;
}

ISR(TIMER1_COMPA_vect)
{
    if (phase == PHASE_HOP) {
        schedule_edge(edge_tick);
        return;
    }
    if (phase != PHASE_EDGE) {
        TIMSK1 &= ~_BV(OCIE1A);
        return;
    }
    if ((int32_t)(clock_now32_isr() - (uint32_t)edge_tick) < 0)
        return;
    level = !level;
    if (level)
        on_rise();
    else
        on_fall();
}

void trigger_encoder_moved(int32_t position)
{
    if (!armed || config.source != TRIGGER_SOURCE_ENCODER || !encoder_started ||
        stop_reason != NO_STOP)
        return;
    int32_t divisor = (int32_t)config.encoder_divisor;
    int32_t moved = position - last_trigger_position;
    if (moved >= divisor)
        last_trigger_position += divisor;
    else if (moved <= -divisor)
        last_trigger_position -= divisor;
    else
        return;
    if (phase == PHASE_ENC_WAIT) {
        pulse_position = last_trigger_position;
        start_encoder_pulse_now();
    } else {
        encoder_pending = 1;
        pending_position = last_trigger_position;
    }
}

void trigger_init(void)
{
    PORTB &= ~_BV(PB1);
    DDRB |= _BV(PB1);
    stop_reason = NO_STOP;
}

static uint8_t period_fits(uint32_t width, uint32_t period)
{
    return period > width && period - width >= MIN_INTERVAL_TICKS &&
           period <= MAX_INTERVAL_TICKS;
}

static uint8_t divisor_valid(uint32_t divisor)
{
    return divisor != 0 && divisor <= 0x7FFFFFFFUL;
}

uint8_t trigger_configure(const msg_configure_t *requested)
{
    if (armed)
        return ERROR_CODE_BAD_STATE;
    uint32_t width = requested->pulse_width_ticks;
    if (width < MIN_INTERVAL_TICKS || width > MAX_INTERVAL_TICKS)
        return ERROR_CODE_BAD_VALUE;
    if (requested->source == TRIGGER_SOURCE_PERIOD) {
        if (!period_fits(width, requested->period_ticks))
            return ERROR_CODE_BAD_VALUE;
    } else if (requested->source == TRIGGER_SOURCE_ENCODER) {
        if (!divisor_valid(requested->encoder_divisor))
            return ERROR_CODE_BAD_VALUE;
    } else {
        return ERROR_CODE_BAD_VALUE;
    }
    memcpy(&config, requested, sizeof config);
    configured = 1;
    return 0;
}

/* Without this, a smaller divisor that the encoder is already past would trigger on every
 * following count until the grid caught up (a burst at the fastest rate allowed). */
static void realign_encoder_grid(int32_t divisor)
{
    int32_t position = encoder_position_isr();
    int32_t moved = position - last_trigger_position;
    if (moved >= divisor)
        last_trigger_position = position - (divisor - 1);
    else if (moved <= -divisor)
        last_trigger_position = position + (divisor - 1);
}

uint8_t trigger_retime(const msg_retime_t *requested)
{
    uint8_t result = 0;
    uint8_t sreg = SREG;
    cli();
    if (!armed) {
        result = ERROR_CODE_BAD_STATE;
    } else if (config.source == TRIGGER_SOURCE_PERIOD) {
        if (period_fits(config.pulse_width_ticks, requested->period_ticks))
            config.period_ticks = requested->period_ticks;
        else
            result = ERROR_CODE_BAD_VALUE;
    } else if (divisor_valid(requested->encoder_divisor)) {
        config.encoder_divisor = requested->encoder_divisor;
        if (encoder_started)
            realign_encoder_grid((int32_t)requested->encoder_divisor);
    } else {
        result = ERROR_CODE_BAD_VALUE;
    }
    SREG = sreg;
    return result;
}

uint8_t trigger_arm(uint64_t now)
{
    uint8_t result = 0;
    uint8_t sreg = SREG;
    cli();
    if (armed || !configured || stopped_pending || event_head != event_tail) {
        result = ERROR_CODE_BAD_STATE;
    } else if (config.start_tick && (int64_t)(config.start_tick - now) < (int64_t)ARM_LEAD_TICKS) {
        result = ERROR_CODE_BAD_VALUE;
    } else {
        triggers = 0;
        level = 0;
        stop_reason = NO_STOP;
        encoder_started = 0;
        encoder_pending = 0;
        armed = 1;
        schedule_edge(config.start_tick ? config.start_tick : now + ARM_LEAD_TICKS);
    }
    SREG = sreg;
    return result;
}

void trigger_stop(uint8_t reason)
{
    uint8_t sreg = SREG;
    cli();
    if (armed) {
        if (level) {
            if (stop_reason == NO_STOP)
                stop_reason = reason;
        } else {
            finish(reason);
        }
    }
    SREG = sreg;
}

uint8_t trigger_is_armed(void)
{
    return armed;
}

uint8_t trigger_output_pending(void)
{
    return event_head != event_tail || stopped_pending;
}

/* The queue has one producer (the compare interrupt, at the head) and one consumer (the
 * main loop, at the tail); the slot at the tail is not written while it is queued, so it is
 * copied with interrupts on. The same holds for `stopped` while `stopped_pending` is set. */
uint8_t trigger_peek_event(msg_trigger_t *event)
{
    uint8_t tail = event_tail;
    if (tail == event_head)
        return 0;
    memcpy(event, &events[tail], sizeof *event);
    return 1;
}

void trigger_drop_event(void)
{
    event_tail = (uint8_t)((event_tail + 1) % EVENT_QUEUE_SIZE);
}

uint8_t trigger_peek_stopped(msg_stopped_t *out)
{
    if (!stopped_pending || event_head != event_tail)
        return 0;
    memcpy(out, &stopped, sizeof *out);
    return 1;
}

void trigger_drop_stopped(void)
{
    stopped_pending = 0;
}

/*
 * harness.c: runs the trigger firmware on simavr (ATmega328P, 16 MHz) for the tests and the
 * jitter benchmark. Built by firmware_bridge.firmware_build.build_harness() with
 *   gcc -O2 harness.c -I/usr/include/simavr -lsimavr -lutil -lm
 * and driven by firmware_bridge.simulator.SimulatedMcu.
 *
 *   harness FIRMWARE.elf --pty LINK --edges FILE [--encoder START_NS:COUNTS_PER_S[:DURATION_NS]]...
 *           [--speed FACTOR] [--hold]
 *
 * What it does:
 *   - UART0 <-> a pty, bridged here at the end of every 20 us step of simulation in both
 *     directions (simavr's uart_pty part writes out only when its thread's 0.5 ms select
 *     times out, a lopsided delay); LINK is made a symlink to the pty's slave, so pyserial
 *     can open LINK.
 *   - Every change of the trigger pin PB1 is written to FILE, line-buffered, as
 *       "<simulated ns> PB1 <level> <wall ns>"
 *     (wall ns: CLOCK_MONOTONIC when the harness simulated the edge, the moment a wire
 *     watcher would see it, to the pacing step)
 *     and every MCU reset (the watchdog's) as "<simulated ns> RESET 1". Simulated time is
 *     counted from the start of the simulation and runs on across resets. Edges made by
 *     Timer1's compare unit get the exact cycle the compare was scheduled for (taken from
 *     the timer's state, because simavr notifies pin changes at the end of the instruction
 *     during which they fell due); other pin changes get the cycle the instruction ended.
 *   - Encoder: PD2 (A) and PD3 (B) are driven as an x4 quadrature signal from a schedule of
 *     segments, each a start time, a signed rate in counts per second (positive: A leads B)
 *     and an optional duration; a segment without one runs until the next segment starts
 *     (or for ever). Counts are placed at start + k / rate, rounded to the CPU cycle, with
 *     avr_cycle_timer_register, so they are exact in simulated time.
 *   - Pacing: simulated time is kept from running ahead of wall time: after each 20 us of
 *     simulation the harness sleeps (timer slack 1 us) while simulated time / FACTOR is more
 *     than 20 us ahead of wall time
 *     since the start (default FACTOR 1: ticks track the wall clock, so a host's clock sync
 *     and its time-outs mean what they would on hardware). When the host is too slow
 *     to keep up, simulated time falls behind; a lag over 20 ms is forgiven (the wall-clock
 *     origin moves) instead of being caught up in a burst, and counted as a slip. FACTOR 0
 *     runs as fast as possible. simavr's own sleep (usleep while the AVR sleeps) is replaced
 *     by this pacing, and simavr's polling of low INT0/INT1 pins is switched off (see
 *     no_level_polling), so a sleeping CPU is simulated in jumps, far faster than real time.
 *   - --hold keeps the CPU in reset until "go" arrives on stdin, so a host can open the pty
 *     first (pyserial flushes input on open) and see BOOT.
 *   - Commands on stdin, one per line: "go"; "quit"; "encoder COUNTS_PER_S" (a new segment
 *     from now on, replacing the rest of the schedule); "pin <port><bit> <0|1>" (drive an
 *     input, e.g. "pin C0 0" for the test build's hang pin).
 *   - Stops on "quit", end of stdin, SIGTERM or SIGINT: it flushes the log, removes LINK and
 *     exits. At exit one line of pacing statistics goes to stderr.
 *
 * What it does not do: no other peripherals or pins are modelled; pin changes the firmware
 * makes on other pins are not logged; simavr's UART counts 11 bit times per byte (it always
 * adds a parity bit), so UART timing is 10 % slower than the real 8N1 line; no GDB, no VCD.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <fcntl.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <sys/prctl.h>
#include <termios.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "avr_extint.h"
#include "avr_ioport.h"
#include "avr_timer.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"

#define MCU_NAME "atmega328p"
#define MCU_HZ 16000000ULL
#define CHUNK_CYCLES 320
#define SLEEP_THRESHOLD_NS 20000LL
#define MAX_LAG_NS 20000000LL
#define MAX_SEGMENTS 64
#define MAX_DRIVEN 16

typedef struct {
    uint64_t start;
    uint64_t end;
    double rate;
} segment_t;

typedef struct {
    char port;
    uint8_t bit;
    uint8_t level;
} driven_pin_t;

static avr_t *avr;
static int pty_master = -1;
static char pty_slave[64];
static avr_irq_t *uart_input;
static int uart_xon;
static uint8_t to_host[4096];
static size_t to_host_used;
static uint64_t to_host_dropped;
static uint8_t to_mcu[512];
static size_t to_mcu_used, to_mcu_done;
static avr_timer_t *timer1;
static FILE *edge_log;
static const char *link_path;

static uint64_t cycle_offset;
static int reset_seen;
static void (*core_reset)(struct avr_t *);
static int last_level = -1;

static segment_t segments[MAX_SEGMENTS];
static int segment_count;
static int segment_index;
static uint64_t segment_counts;
static uint8_t quadrature_phase;
static const uint8_t GRAY_A[4] = {0, 1, 1, 0};
static const uint8_t GRAY_B[4] = {0, 0, 1, 1};

static driven_pin_t driven[MAX_DRIVEN];
static int driven_count;

static volatile sig_atomic_t stop_requested;
static double speed = 1.0;
static uint64_t slips;
static int64_t worst_lag_ns;

static uint64_t sim_cycles(void)
{
    return cycle_offset + avr->cycle;
}

static uint64_t cycles_to_ns(uint64_t cycles)
{
    return cycles * 1000000000ULL / MCU_HZ;
}

static uint64_t ns_to_cycles(uint64_t ns)
{
    return ns * MCU_HZ / 1000000000ULL;
}

static int64_t wall_ns(void)
{
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (int64_t)now.tv_sec * 1000000000LL + now.tv_nsec;
}

static void cleanup_and_exit(int status)
{
    fflush(stdout);
    if (edge_log)
        fflush(edge_log);
    if (link_path)
        unlink(link_path);
    fprintf(stderr,
            "harness: simulated %.3f s, pacing slips %llu, worst lag %.3f ms, "
            "bytes to host dropped %llu\n",
            cycles_to_ns(sim_cycles()) / 1e9, (unsigned long long)slips, worst_lag_ns / 1e6,
            (unsigned long long)to_host_dropped);
    fflush(stderr);
    _exit(status);
}

static void on_signal(int signal_number)
{
    (void)signal_number;
    stop_requested = 1;
}

static uint64_t compare_edge_cycle(void)
{
    if (!timer1 || !timer1->tov_cycles)
        return avr->cycle;
    uint64_t edge = timer1->tov_base + timer1->comp[AVR_TIMER_COMPA].comp_cycles;
    while (edge > avr->cycle && edge >= timer1->tov_cycles)
        edge -= timer1->tov_cycles;
    if (edge > avr->cycle || avr->cycle - edge > 8)
        return avr->cycle;
    return edge;
}

static void trigger_pin_changed(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    int level = (int)(value & 1);
    if (level == last_level)
        return;
    last_level = level;
    uint64_t cycle = (value & AVR_IOPORT_OUTPUT) ? compare_edge_cycle() : avr->cycle;
    fprintf(edge_log, "%llu PB1 %d %lld\n", (unsigned long long)cycles_to_ns(cycle_offset + cycle),
            level, (long long)wall_ns());
}

static void drive_pin(char port, uint8_t bit, uint8_t level)
{
    avr_irq_t *irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(port), bit);
    if (irq)
        avr_raise_irq(irq, level);
}

static void remember_pin(char port, uint8_t bit, uint8_t level)
{
    for (int i = 0; i < driven_count; i++)
        if (driven[i].port == port && driven[i].bit == bit) {
            driven[i].level = level;
            return;
        }
    if (driven_count < MAX_DRIVEN)
        driven[driven_count++] = (driven_pin_t){port, bit, level};
}

static void set_pin(char port, uint8_t bit, uint8_t level)
{
    remember_pin(port, bit, level);
    drive_pin(port, bit, level);
}

/* Absolute simulated cycle of the next count from the current position in the schedule, or
 * 0 when the schedule is done. Moves on to the next segment as segments run out. */
static uint64_t next_count_cycle(void)
{
    while (segment_index < segment_count) {
        segment_t *s = &segments[segment_index];
        uint64_t end = s->end;
        if (segment_index + 1 < segment_count && segments[segment_index + 1].start < end)
            end = segments[segment_index + 1].start;
        if (s->rate != 0.0) {
            double step = (double)MCU_HZ / fabs(s->rate);
            uint64_t when = s->start + (uint64_t)llround((double)(segment_counts + 1) * step);
            if (when < end)
                return when;
        }
        segment_index++;
        segment_counts = 0;
    }
    return 0;
}

static avr_cycle_count_t encoder_count(struct avr_t *core, avr_cycle_count_t when, void *param)
{
    (void)core;
    (void)param;
    segment_t *s = &segments[segment_index];
    quadrature_phase = (uint8_t)((quadrature_phase + (s->rate > 0 ? 1 : 3)) & 3);
    segment_counts++;
    set_pin('D', 2, GRAY_A[quadrature_phase]);
    set_pin('D', 3, GRAY_B[quadrature_phase]);
    uint64_t next = next_count_cycle();
    if (!next)
        return 0;
    uint64_t next_avr = next - cycle_offset;
    return next_avr > when ? next_avr : when + 1;
}

static void schedule_encoder(void)
{
    avr_cycle_timer_cancel(avr, encoder_count, NULL);
    uint64_t next = next_count_cycle();
    if (!next)
        return;
    uint64_t now = sim_cycles();
    avr_cycle_timer_register(avr, next > now ? next - now : 1, encoder_count, NULL);
}

static void encoder_from_now(double rate)
{
    segments[0] = (segment_t){sim_cycles(), UINT64_MAX, rate};
    segment_count = 1;
    segment_index = 0;
    segment_counts = 0;
    schedule_encoder();
}

static int parse_segment(const char *text)
{
    unsigned long long start_ns = 0, duration_ns = 0;
    double rate = 0.0;
    int n = sscanf(text, "%llu:%lf:%llu", &start_ns, &rate, &duration_ns);
    if (n < 2 || segment_count == MAX_SEGMENTS)
        return -1;
    if (segment_count && ns_to_cycles(start_ns) < segments[segment_count - 1].start)
        return -1;
    uint64_t start = ns_to_cycles(start_ns);
    uint64_t end = n == 3 ? start + ns_to_cycles(duration_ns) : UINT64_MAX;
    segments[segment_count++] = (segment_t){start, end, rate};
    return 0;
}

static void mcu_reset(struct avr_t *core)
{
    core_reset(core);
    reset_seen = 1;
}

/* simavr 1.6 polls an INT pin that is low every cycle ("strict" level triggering, on by
 * default and again after every reset), whatever the pin's sense control says, and the poll
 * ends only when the pin goes high. The encoder pins sit low for long stretches, so the CPU
 * would never sleep in simulation and the harness would barely keep up with wall time. The
 * firmware senses any change on INT0 and INT1, never the low level, so polling is switched
 * off. */
static void no_level_polling(void)
{
    avr_extint_set_strict_lvl_trig(avr, 0, 0);
    avr_extint_set_strict_lvl_trig(avr, 1, 0);
}

static void after_reset(uint64_t cycle_before)
{
    if (avr->cycle < cycle_before)
        cycle_offset += cycle_before - avr->cycle;
    no_level_polling();
    fprintf(edge_log, "%llu RESET 1\n", (unsigned long long)cycles_to_ns(sim_cycles()));
    for (int i = 0; i < driven_count; i++) {
        drive_pin(driven[i].port, driven[i].bit, (uint8_t)!driven[i].level);
        drive_pin(driven[i].port, driven[i].bit, driven[i].level);
    }
    schedule_encoder();
}

static void no_sleep(avr_t *core, avr_cycle_count_t how_long)
{
    (void)core;
    (void)how_long;
}

static int command(char *line, int *go)
{
    char port = 0;
    unsigned bit = 0, level = 0;
    double rate = 0.0;
    line[strcspn(line, "\r\n")] = 0;
    if (!strcmp(line, "go")) {
        *go = 1;
    } else if (!strcmp(line, "quit")) {
        return -1;
    } else if (sscanf(line, "encoder %lf", &rate) == 1) {
        encoder_from_now(rate);
    } else if (sscanf(line, "pin %c%u %u", &port, &bit, &level) == 3 && port >= 'B' &&
               port <= 'D' && bit < 8) {
        set_pin(port, (uint8_t)bit, (uint8_t)(level != 0));
    } else if (line[0]) {
        fprintf(stderr, "harness: unknown command '%s'\n", line);
    }
    return 0;
}

/* Reads and runs whole lines from stdin without blocking; -1 on "quit" or end of input. */
static int read_commands(int *go)
{
    static char pending[512];
    static size_t used;
    struct pollfd fd = {.fd = STDIN_FILENO, .events = POLLIN};
    while (poll(&fd, 1, 0) > 0) {
        if (fd.revents & (POLLERR | POLLNVAL))
            return -1;
        ssize_t got = read(STDIN_FILENO, pending + used, sizeof pending - 1 - used);
        if (got <= 0)
            return -1;
        used += (size_t)got;
        pending[used] = 0;
        char *line;
        while ((line = strchr(pending, '\n')) != NULL) {
            *line = 0;
            if (command(pending, go) < 0)
                return -1;
            size_t consumed = (size_t)(line - pending) + 1;
            memmove(pending, pending + consumed, used - consumed + 1);
            used -= consumed;
        }
        if (used == sizeof pending - 1)
            used = 0;
    }
    return 0;
}

static avr_timer_t *find_timer(char name)
{
    for (avr_io_t *io = avr->io_port; io; io = io->next)
        if (io->kind && !strcmp(io->kind, "timer") && ((avr_timer_t *)io)->name == name)
            return (avr_timer_t *)io;
    return NULL;
}

/* The UART bridge. Bytes the firmware sends are collected as the UART puts them out and
 * written to the pty at the end of each chunk; bytes from the host are read at the end of
 * each chunk and handed to the UART while it signals room (XON). Both directions thus wait
 * at most one chunk of simulated time, the same either way. Bytes from the host wait until
 * the UART first signals room (its receiver enabled), so what a host sends before the
 * firmware has started is not lost; after a reset they are, as on hardware. */
static void uart_byte_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (to_host_used < sizeof to_host)
        to_host[to_host_used++] = (uint8_t)value;
    else
        to_host_dropped++;
}

static void feed_uart(void)
{
    while (uart_xon && to_mcu_done < to_mcu_used)
        avr_raise_irq(uart_input, to_mcu[to_mcu_done++]);
}

static void uart_room(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    (void)param;
    uart_xon = 1;
    feed_uart();
}

static void uart_full(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value)
        uart_xon = 0;
}

/* Write what the firmware sent, read what the host sent. With no reader on the slave side
 * the pty keeps what it can hold; what does not fit in it and in `to_host` is counted as
 * dropped (a host that does not read its port loses bytes, as on a real line). */
static void service_uart(void)
{
    if (to_host_used) {
        ssize_t n = write(pty_master, to_host, to_host_used);
        if (n > 0) {
            to_host_used -= (size_t)n;
            memmove(to_host, to_host + n, to_host_used);
        }
    }
    if (to_mcu_done == to_mcu_used) {
        ssize_t n = read(pty_master, to_mcu, sizeof to_mcu);
        to_mcu_done = 0;
        to_mcu_used = n > 0 ? (size_t)n : 0;
    }
    feed_uart();
}

static void connect_uart(void)
{
    int slave;
    if (openpty(&pty_master, &slave, pty_slave, NULL, NULL) < 0) {
        fprintf(stderr, "harness: cannot open a pty: %s\n", strerror(errno));
        exit(1);
    }
    struct termios raw;
    tcgetattr(pty_master, &raw);
    cfmakeraw(&raw);
    tcsetattr(pty_master, TCSANOW, &raw);
    tcgetattr(slave, &raw);
    cfmakeraw(&raw);
    tcsetattr(slave, TCSANOW, &raw);
    close(slave);
    fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);

    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(uint32_t)(AVR_UART_FLAG_POLL_SLEEP | AVR_UART_FLAG_STDIO);
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    uart_input = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            uart_byte_out, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
                            uart_room, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
                            uart_full, NULL);

    unlink(link_path);
    if (symlink(pty_slave, link_path) != 0) {
        fprintf(stderr, "harness: cannot link %s -> %s: %s\n", link_path, pty_slave,
                strerror(errno));
        exit(1);
    }
}

static void usage(void)
{
    fprintf(stderr, "usage: harness FIRMWARE.elf --pty LINK --edges FILE "
                    "[--encoder START_NS:COUNTS_PER_S[:DURATION_NS]]... [--speed FACTOR] "
                    "[--hold]\n");
    exit(2);
}

static void pace(uint64_t origin_cycles, int64_t *origin_wall)
{
    if (speed <= 0.0)
        return;
    int64_t simulated = (int64_t)((double)cycles_to_ns(sim_cycles() - origin_cycles) / speed);
    int64_t ahead = simulated - (wall_ns() - *origin_wall);
    if (ahead > SLEEP_THRESHOLD_NS) {
        struct timespec pause = {ahead / 1000000000LL, ahead % 1000000000LL};
        nanosleep(&pause, NULL);
    } else if (-ahead > MAX_LAG_NS) {
        slips++;
        if (-ahead > worst_lag_ns)
            worst_lag_ns = -ahead;
        *origin_wall -= ahead;
    }
}

int main(int argc, char **argv)
{
    const char *firmware = NULL, *edges = NULL;
    int hold = 0;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--pty") && i + 1 < argc)
            link_path = argv[++i];
        else if (!strcmp(argv[i], "--edges") && i + 1 < argc)
            edges = argv[++i];
        else if (!strcmp(argv[i], "--encoder") && i + 1 < argc) {
            if (parse_segment(argv[++i]) < 0) {
                fprintf(stderr, "harness: bad --encoder segment '%s'\n", argv[i]);
                usage();
            }
        } else if (!strcmp(argv[i], "--speed") && i + 1 < argc)
            speed = atof(argv[++i]);
        else if (!strcmp(argv[i], "--hold"))
            hold = 1;
        else if (argv[i][0] != '-' && !firmware)
            firmware = argv[i];
        else
            usage();
    }
    if (!firmware || !link_path || !edges)
        usage();

    edge_log = fopen(edges, "w");
    if (!edge_log) {
        fprintf(stderr, "harness: cannot open %s: %s\n", edges, strerror(errno));
        return 1;
    }
    setvbuf(edge_log, NULL, _IOLBF, 0);

    elf_firmware_t image;
    memset(&image, 0, sizeof image);
    if (elf_read_firmware(firmware, &image) != 0) {
        fprintf(stderr, "harness: cannot read %s\n", firmware);
        return 1;
    }
    strcpy(image.mmcu, MCU_NAME);
    image.frequency = MCU_HZ;
    avr = avr_make_mcu_by_name(MCU_NAME);
    if (!avr) {
        fprintf(stderr, "harness: simavr does not know %s\n", MCU_NAME);
        return 1;
    }
    avr_init(avr);
    avr_load_firmware(avr, &image);
    avr->sleep = no_sleep;
    core_reset = avr->reset;
    avr->reset = mcu_reset;
    timer1 = find_timer('1');

    prctl(PR_SET_TIMERSLACK, 1000UL);
    signal(SIGTERM, on_signal);
    signal(SIGINT, on_signal);
    signal(SIGPIPE, SIG_IGN);

    connect_uart();
    no_level_polling();
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 1),
                            trigger_pin_changed, NULL);
    set_pin('D', 2, 0);
    set_pin('D', 3, 0);

    int go = !hold;
    while (!go) {
        if (stop_requested || read_commands(&go) < 0)
            cleanup_and_exit(0);
        if (!go) {
            struct pollfd fd = {.fd = STDIN_FILENO, .events = POLLIN};
            poll(&fd, 1, 50);
        }
    }
    schedule_encoder();

    uint64_t origin_cycles = sim_cycles();
    int64_t origin_wall = wall_ns();
    unsigned chunks = 0;
    for (;;) {
        uint64_t target = avr->cycle + CHUNK_CYCLES;
        while (avr->cycle < target) {
            uint64_t before = avr->cycle;
            int state = avr_run(avr);
            if (reset_seen) {
                reset_seen = 0;
                after_reset(before);
                break;
            }
            if (state == cpu_Done || state == cpu_Crashed) {
                fprintf(stderr, "harness: simulation ended (cpu state %d)\n", state);
                cleanup_and_exit(3);
            }
        }
        service_uart();
        pace(origin_cycles, &origin_wall);
        if ((++chunks & 31) == 0) {
            if (stop_requested || read_commands(&go) < 0)
                cleanup_and_exit(0);
        }
    }
}

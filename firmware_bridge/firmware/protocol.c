/*
 * protocol.c: packet parser, command dispatch and packet sending (see protocol.h).
 *
 * Packets are built whole in a stack buffer and copied into the transmit ring only when it
 * has room for all of them, so the ring never holds a partial packet.
 */
#include "protocol.h"

#include <string.h>
#include <util/crc16.h>

#include "clock.h"
#include "config.h"
#include "encoder.h"
#include "messages.h"
#include "trigger.h"
#include "uart.h"

#define PACKET_MAX (MSG_MAX_LEN + 4)
/* Room kept free for the reply to the packet being parsed. */
#define REPLY_ROOM PACKET_MAX
#define ERROR_PACKET (MSG_SIZE_ERROR + 6)

/* The parser's bytes are window[begin ... end): received bytes are appended in batches and
 * parsed once per batch; dropping bytes moves `begin` only, and the window is moved back
 * to its start when less than a packet's room is left, so a resync that drops one byte at a
 * time costs no copying. */
#define WINDOW (2 * PACKET_MAX)
static uint8_t window[WINDOW];
static uint16_t stamps[WINDOW];
static uint8_t begin;
static uint8_t end;

static uint8_t expected_seq;
static uint8_t tx_seq;
static uint64_t last_valid_tick;
static uint32_t dead_man_ticks;

static uint16_t crc16(const uint8_t *data, uint8_t length)
{
    uint16_t crc = 0xFFFF;
    for (uint8_t i = 0; i < length; i++)
        crc = _crc_xmodem_update(crc, data[i]);
    return crc;
}

static uint8_t send_packet(uint8_t id, const void *payload, uint8_t size)
{
    uint8_t packet[PACKET_MAX];
    uint8_t total = (uint8_t)(size + 6);
    if (uart_tx_free() < total)
        return 0;
    packet[0] = MSG_START_BYTE;
    packet[1] = (uint8_t)(size + 2);
    packet[2] = tx_seq;
    packet[3] = id;
    memcpy(&packet[4], payload, size);
    uint16_t crc = crc16(&packet[1], (uint8_t)(size + 3));
    packet[4 + size] = (uint8_t)crc;
    packet[5 + size] = (uint8_t)(crc >> 8);
    uart_write(packet, total);
    tx_seq++;
    return 1;
}

static void send_error(uint8_t code, uint8_t detail, uint8_t seq)
{
    msg_error_t error = {.code = code, .detail = detail, .rejected_seq = seq};
    send_packet(MSG_ID_ERROR, &error, sizeof error);
}

/* Best effort: only when the transmit ring has room beyond what replies may need, so a
 * stream of garbage never holds up the answers to the valid packets in it. */
static void framing_error(uint8_t code, uint8_t detail, uint8_t seq)
{
    if (uart_tx_free() >= 2 * REPLY_ROOM + ERROR_PACKET)
        send_error(code, detail, seq);
}

static void send_ack(uint8_t seq)
{
    msg_ack_t ack = {.acked_seq = seq};
    send_packet(MSG_ID_ACK, &ack, sizeof ack);
}

void protocol_send_boot(uint8_t cause)
{
    msg_boot_t boot = {.cause = cause};
    send_packet(MSG_ID_BOOT, &boot, sizeof boot);
}

static int16_t payload_size(uint8_t id)
{
    switch (id) {
#define SIZE_CASE(name, id_value, size) \
    case id_value:                      \
        return size;
        MSG_TO_MCU_LIST(SIZE_CASE)
#undef SIZE_CASE
    default:
        return -1;
    }
}

static void command(uint8_t seq, uint8_t id, const uint8_t *payload, uint64_t received)
{
    uint8_t refused = 0;
    switch (id) {
    case MSG_ID_PING: {
        msg_pong_t pong;
        memcpy(&pong.token, payload, sizeof pong.token);
        pong.tick = received;
        send_packet(MSG_ID_PONG, &pong, sizeof pong);
        return;
    }
    case MSG_ID_GET_POSITION: {
        msg_position_t reply;
        reply.position = encoder_position();
        reply.tick = clock_now();
        send_packet(MSG_ID_POSITION, &reply, sizeof reply);
        return;
    }
    case MSG_ID_CONFIGURE: {
        msg_configure_t config;
        memcpy(&config, payload, sizeof config);
        refused = trigger_configure(&config);
        break;
    }
    case MSG_ID_RETIME: {
        msg_retime_t retime;
        memcpy(&retime, payload, sizeof retime);
        refused = trigger_retime(&retime);
        break;
    }
    case MSG_ID_ARM:
        refused = trigger_arm(clock_now());
        break;
    case MSG_ID_DISARM:
        trigger_stop(STOP_REASON_DISARMED);
        break;
    case MSG_ID_SET_DEAD_MAN: {
        msg_set_dead_man_t dead_man;
        memcpy(&dead_man, payload, sizeof dead_man);
        dead_man_ticks = (uint32_t)dead_man.timeout_ms * (TICK_HZ / 1000UL);
        break;
    }
    default:
        return;
    }
    if (refused)
        send_error(refused, id, seq);
    else
        send_ack(seq);
}

static void hello(void)
{
    msg_hello_reply_t reply = {
        .version_major = PROTOCOL_VERSION_MAJOR,
        .version_minor = PROTOCOL_VERSION_MINOR,
        .table_hash = MSG_TABLE_HASH,
        .tick_hz = TICK_HZ,
    };
    reply.tick = clock_now();
    send_packet(MSG_ID_HELLO_REPLY, &reply, sizeof reply);
}

static void handle_packet(uint8_t seq, uint8_t id, const uint8_t *payload, uint8_t size, uint16_t stamp)
{
    uint64_t received = clock_extend16(stamp, clock_now());
    if (id == MSG_ID_HELLO) {
        if (size != MSG_SIZE_HELLO) {
            send_error(ERROR_CODE_BAD_PAYLOAD, id, seq);
            return;
        }
        expected_seq = (uint8_t)(seq + 1);
        last_valid_tick = received;
        hello();
        return;
    }
    if (seq != expected_seq) {
        send_error(ERROR_CODE_OUT_OF_SEQUENCE, expected_seq, seq);
        return;
    }
    expected_seq++;
    int16_t wanted = payload_size(id);
    if (wanted < 0) {
        send_error(ERROR_CODE_UNKNOWN_MESSAGE, id, seq);
        return;
    }
    if (size != wanted) {
        send_error(ERROR_CODE_BAD_PAYLOAD, id, seq);
        return;
    }
    last_valid_tick = received;
    command(seq, id, payload, received);
}

static void drop(uint8_t count)
{
    begin = (uint8_t)(begin + count);
    if (begin == end)
        begin = end = 0;
}

/* Move the window's bytes to its start; afterwards there is room for at least PACKET_MAX
 * more (a waiting packet or candidate never spans more than PACKET_MAX). */
static void compact(void)
{
    uint8_t fill = (uint8_t)(end - begin);
    memmove(window, window + begin, fill);
    memmove(stamps, stamps + begin, (size_t)fill * sizeof stamps[0]);
    begin = 0;
    end = fill;
}

/* Consume what the window holds: packets are handled, garbage answered and dropped. Returns
 * 1 when a complete packet has to wait for transmit room for its reply, 0 when the window is
 * empty or holds the start of a packet still arriving. */
static uint8_t parse(void)
{
    for (;;) {
        while (begin < end && window[begin] != MSG_START_BYTE)
            drop(1);
        const uint8_t *bytes = &window[begin];
        uint8_t fill = (uint8_t)(end - begin);
        if (fill < 2)
            return 0;
        uint8_t length = bytes[1];
        if (length < 2 || length > MSG_MAX_LEN) {
            framing_error(ERROR_CODE_BAD_LENGTH, length, 0);
            drop(1);
            continue;
        }
        uint8_t total = (uint8_t)(length + 4);
        if (fill < total)
            return 0;
        uint16_t received = (uint16_t)(bytes[length + 2] | (bytes[length + 3] << 8));
        if (crc16(&bytes[1], (uint8_t)(length + 1)) != received) {
            framing_error(ERROR_CODE_BAD_CRC, bytes[3], bytes[2]);
            drop(1);
            continue;
        }
        if (uart_tx_free() < REPLY_ROOM)
            return 1;
        handle_packet(bytes[2], bytes[3], &bytes[4], (uint8_t)(length - 2), stamps[begin + total - 1]);
        drop(total);
    }
}

static void give_up_partial(void)
{
    while (begin < end) {
        uint8_t fill = (uint8_t)(end - begin);
        framing_error(ERROR_CODE_BAD_LENGTH, fill > 1 ? window[begin + 1] : 0,
                      fill > 2 ? window[begin + 2] : 0);
        drop(1);
        if (parse())
            return;
    }
}

/* Events leave room for the replies (2 * REPLY_ROOM), so a flood of TRIGGERs (a trigger
 * rate the line cannot carry) loses TRIGGERs, never the host's ability to command. */
static void send_output(void)
{
    msg_trigger_t event;
    while (uart_tx_free() >= 2 * REPLY_ROOM + MSG_SIZE_TRIGGER + 6 && trigger_peek_event(&event)) {
        send_packet(MSG_ID_TRIGGER, &event, sizeof event);
        trigger_drop_event();
    }
    msg_stopped_t stopped;
    if (uart_tx_free() >= 2 * REPLY_ROOM + MSG_SIZE_STOPPED + 6 && trigger_peek_stopped(&stopped)) {
        send_packet(MSG_ID_STOPPED, &stopped, sizeof stopped);
        trigger_drop_stopped();
    }
}

void protocol_poll(void)
{
    send_output();
    uint8_t blocked = parse();
    uint8_t budget = RX_RING_SIZE;
    while (!blocked && budget) {
        if (WINDOW - end < PACKET_MAX)
            compact();
        uint8_t got = 0;
        while (end < WINDOW && budget && uart_read(&window[end], &stamps[end])) {
            end++;
            budget--;
            got = 1;
        }
        if (!got)
            break;
        blocked = parse();
    }
    uint64_t now = clock_now();
    if (!blocked && begin < end && !uart_rx_pending() &&
        now - clock_extend16(stamps[end - 1], now) > INTERBYTE_TIMEOUT_TICKS)
        give_up_partial();
    if (dead_man_ticks && trigger_is_armed() && now - last_valid_tick > dead_man_ticks)
        trigger_stop(STOP_REASON_DEAD_MAN);
}

uint8_t protocol_busy(void)
{
    return trigger_output_pending() || uart_rx_pending();
}

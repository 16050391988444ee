/*
 * protocol.h: the firmware's side of the packet protocol in firmware_bridge/messages.py.
 *
 * protocol_poll(), called from the main loop, does everything the host link needs:
 *   - sends queued TRIGGER events, then the STOPPED of a finished run, leaving room in the
 *     transmit ring for replies (a TRIGGER rate the line cannot carry loses TRIGGERs, which
 *     shows as gaps in trigger_seq, but the host can still command, DISARM included);
 *   - feeds received bytes to the packet parser in batches, at most RX_RING_SIZE bytes per
 *     call, so the main loop (and the watchdog reset in it) comes round even when bytes
 *     arrive faster than they are parsed; a complete packet is handled only when the
 *     transmit ring has room for its reply, else it waits in the parser and further bytes
 *     in the receive ring (so a reply is never dropped);
 *   - drops a packet whose bytes stopped coming for INTERBYTE_TIMEOUT_TICKS;
 *   - fires the dead-man: armed, a timeout set, and no valid packet for that long.
 *
 * Parser: the same rules as the host's PacketDecoder (firmware_bridge/packets.py). It holds
 * up to MAX_LEN + 4 bytes; on a bad LEN or CRC it drops the start byte only and searches
 * again from the next byte, so a valid packet hidden behind garbage is still found. Answers:
 *   bad LEN (outside 2 ... MAX_LEN)  ERROR(BAD_LENGTH, detail = the LEN byte, seq 0)
 *   truncated (inter-byte timeout)   ERROR(BAD_LENGTH, detail = the LEN byte, seq byte or 0)
 *   bad CRC                          ERROR(BAD_CRC, detail = the id byte, the seq byte)
 *   good CRC, SEQ not the expected   ERROR(OUT_OF_SEQUENCE, detail = expected, seq); ignored
 *   unknown id (or a to-host id)     ERROR(UNKNOWN_MESSAGE, id, seq)
 *   payload size not the message's   ERROR(BAD_PAYLOAD, id, seq)
 *   command refused                  ERROR(BAD_STATE or BAD_VALUE, id, seq)
 * Framing errors (the first three) are sent only when the transmit ring has room to spare;
 * under a flood of garbage some are not sent, the replies to valid packets always are.
 *
 * Sequence numbers: HELLO is taken with any number and sets the expectation to its number
 * + 1. Any other packet with a good CRC and the expected number moves the expectation on,
 * even when it is then rejected (unknown id, bad payload, bad state or value), because the
 * host has used that number; a packet with a bad CRC or another number does not.
 *
 * "Valid packet" for the dead-man: good CRC, expected number (or HELLO), known id and right
 * payload size, whether or not the command is then accepted.
 *
 * Times: PONG.tick is the tick at which the PING's last byte (its CRC high byte) was
 * received, stamped in the UART receive interrupt (see uart.h for how close). HELLO_REPLY.tick and POSITION.tick are
 * read when the reply is built.
 *
 * Replies: HELLO -> HELLO_REPLY, PING -> PONG, GET_POSITION -> POSITION; CONFIGURE, ARM,
 * RETIME, DISARM and SET_DEAD_MAN -> ACK(their seq) when accepted. DISARM is ACKed also when
 * nothing is armed (and then no STOPPED follows). SET_DEAD_MAN is accepted armed or not;
 * RETIME only while armed, CONFIGURE only while not.
 */
#ifndef PROTOCOL_H
#define PROTOCOL_H

#include <stdint.h>

void protocol_send_boot(uint8_t cause);

void protocol_poll(void);

/* Work is waiting that the next protocol_poll() can do. */
uint8_t protocol_busy(void);

#endif /* PROTOCOL_H */

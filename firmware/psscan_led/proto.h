/*
 * proto.h - psscan LED controller: line protocol parser and state machine.
 *
 * Pure, portable C99: no AVR headers, no stdio, no heap. The same file is
 * compiled into the firmware (avr-gcc), the native unit test and the
 * libFuzzer target (clang), so everything the board decides is decided here.
 * The hardware layer (fw_main.c) only moves bytes in and out, calls
 * proto_tick_ms() once per millisecond and drives the pins from proto.led.
 *
 * The protocol itself is specified in ../PROTOCOL.md.
 */
#ifndef PSSCAN_PROTO_H
#define PSSCAN_PROTO_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define PROTO_VERSION_FW   "1.0.0"
#define PROTO_VERSION      "1"
#define PROTO_NUM_LEDS     10

/* Identity string shared by the READY banner and the ID answer. */
#define PROTO_IDENT "psscan-led fw=" PROTO_VERSION_FW " proto=" PROTO_VERSION " leds=10"
#define PROTO_BANNER "READY " PROTO_IDENT "\n"

/* Longest accepted line, not counting '\n' (and '\r', which is dropped). */
#define PROTO_MAX_LINE     32
/* Longest answer including its '\n' ("OK STATE OFF timeout=60000 tripped=1\n"
 * is 37 bytes; the ID answer is 42). Callers pass a buffer at least this big. */
#define PROTO_MAX_REPLY    48

#define PROTO_TIMEOUT_DEFAULT_MS 3000u
#define PROTO_TIMEOUT_MIN_MS     100u
#define PROTO_TIMEOUT_MAX_MS     60000u

/* proto.led value meaning "all LEDs off". */
#define PROTO_LED_OFF (-1)

/* Error codes, see PROTOCOL.md. */
enum proto_err {
    PROTO_ERR_UNKNOWN_CMD = 1,
    PROTO_ERR_BAD_ARG = 2,
    PROTO_ERR_TOO_LONG = 3,
    PROTO_ERR_RANGE = 4,
    PROTO_ERR_BAD_CHAR = 5
};

typedef struct proto {
    /* ---- observable state (read by the hardware layer and by tests) ---- */
    int8_t led;           /* PROTO_LED_OFF or 0..9: the one LED that is on  */
    uint8_t tripped;      /* 1: the silence timeout switched an LED off
                             since the last successful ON                    */
    uint16_t timeout_ms;  /* host-silence timeout, 100..60000               */
    uint16_t silence_ms;  /* ms since the last successfully executed command
                             (saturates at timeout_ms + 1)                   */

    /* ---- line assembly ---- */
    uint8_t len;          /* bytes stored in line[]                         */
    uint8_t too_long;     /* line exceeded PROTO_MAX_LINE: discarding to \n */
    uint8_t bad_char;     /* line contained a non-printable / >=0x80 byte   */
    char line[PROTO_MAX_LINE];
} proto_t;

/* Power-up state: all LEDs off, default timeout, not tripped, empty line. */
void proto_init(proto_t *p);

/*
 * Feed one received byte. When the byte completes a line ('\n'), the line is
 * executed and its single answer (terminated by '\n') is written to out, which
 * must hold PROTO_MAX_REPLY bytes; the answer length is returned. Any other
 * byte returns 0 and writes nothing. Never writes past out[PROTO_MAX_REPLY-1].
 */
uint8_t proto_feed(proto_t *p, uint8_t byte, char *out);

/*
 * Advance the host-silence clock by one millisecond. Returns 1 when this tick
 * switched an LED off because the host was silent for longer than timeout_ms,
 * else 0. Produces no output (the protocol has no unsolicited messages).
 */
uint8_t proto_tick_ms(proto_t *p);

#ifdef __cplusplus
}
#endif

#endif /* PSSCAN_PROTO_H */

/*
 * proto.c - psscan LED controller: line protocol parser and state machine.
 * See proto.h for the interface and ../PROTOCOL.md for the protocol.
 *
 * Rules that shape this file:
 *  - Every '\n' produces exactly one answer; no other byte produces output.
 *  - Only a command that is answered "OK ..." changes state (LED, timeout,
 *    tripped flag, silence clock). A rejected line changes nothing.
 *  - No stdio/printf: numbers are formatted by hand to keep the AVR image
 *    small, and every write into the answer buffer is bounds checked.
 */
#include "proto.h"

#include <string.h>

/* --- answer writer ------------------------------------------------------ */

typedef struct {
    char *buf;
    uint8_t n;
} writer_t;

/* Room for text; the last byte of the buffer is reserved for '\n'. */
#define WR_TEXT_MAX (PROTO_MAX_REPLY - 1)

static void put_s(writer_t *w, const char *s)
{
    while (*s && w->n < WR_TEXT_MAX)
        w->buf[w->n++] = *s++;
}

static void put_u(writer_t *w, uint16_t v)
{
    char digits[5];
    uint8_t k = 0;
    do {
        digits[k++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v && k < sizeof digits);
    while (k && w->n < WR_TEXT_MAX)
        w->buf[w->n++] = digits[--k];
}

static uint8_t finish(writer_t *w)
{
    w->buf[w->n++] = '\n'; /* n <= WR_TEXT_MAX here, so this fits */
    return w->n;
}

static uint8_t reply_err(char *out, enum proto_err code)
{
    static const char *const reason[] = {
        "",                  /* unused: codes start at 1 */
        "unknown command",   /* PROTO_ERR_UNKNOWN_CMD */
        "bad argument",      /* PROTO_ERR_BAD_ARG     */
        "line too long",     /* PROTO_ERR_TOO_LONG    */
        "out of range",      /* PROTO_ERR_RANGE       */
        "bad character",     /* PROTO_ERR_BAD_CHAR    */
    };
    writer_t w = {out, 0};
    put_s(&w, "ERR ");
    put_u(&w, (uint16_t)code);
    put_s(&w, " ");
    put_s(&w, reason[code]);
    return finish(&w);
}

/* --- state -------------------------------------------------------------- */

void proto_init(proto_t *p)
{
    memset(p, 0, sizeof *p);
    p->led = PROTO_LED_OFF;
    p->timeout_ms = PROTO_TIMEOUT_DEFAULT_MS;
}

uint8_t proto_tick_ms(proto_t *p)
{
    /* Saturate just past the timeout: enough to stay "expired" without
     * wrapping around during very long silences. */
    if (p->silence_ms <= p->timeout_ms)
        p->silence_ms++;
    if (p->silence_ms > p->timeout_ms && p->led != PROTO_LED_OFF) {
        p->led = PROTO_LED_OFF;
        p->tripped = 1;
        return 1;
    }
    return 0;
}

/* --- line execution ----------------------------------------------------- */

/* Compare the command word (not NUL terminated) with a literal. */
static int word_is(const char *word, uint8_t len, const char *lit)
{
    return strlen(lit) == len && memcmp(word, lit, len) == 0;
}

/*
 * Parse a decimal argument: one or more ASCII digits and nothing else.
 * Leading zeros are allowed; values above 65535 saturate (they are out of
 * range for every command anyway). Returns 0 if the text is not a number.
 */
static int parse_uint(const char *s, uint8_t len, uint16_t *value)
{
    uint32_t v = 0;
    uint8_t i;
    if (len == 0)
        return 0;
    for (i = 0; i < len; i++) {
        if (s[i] < '0' || s[i] > '9')
            return 0;
        v = v * 10u + (uint32_t)(s[i] - '0');
        if (v > 65535u)
            v = 65535u + 1u; /* saturate, keep scanning for non-digits */
    }
    *value = v > 65535u ? 65535u : (uint16_t)v;
    return 1;
}

static uint8_t execute(proto_t *p, char *out)
{
    enum { C_ID, C_ON, C_OFF, C_STATE, C_TIMEOUT, C_PING } cmd;
    const char *line = p->line;
    uint8_t len = p->len;
    uint8_t wlen = 0;
    const char *arg = 0;
    uint8_t alen = 0;
    uint16_t val = 0;
    writer_t w = {out, 0};

    /* Split at the first space: "<WORD>" or "<WORD> <ARG>". */
    while (wlen < len && line[wlen] != ' ')
        wlen++;
    if (wlen < len) {
        arg = line + wlen + 1;
        alen = (uint8_t)(len - wlen - 1);
    }

    if (word_is(line, wlen, "ID"))
        cmd = C_ID;
    else if (word_is(line, wlen, "ON"))
        cmd = C_ON;
    else if (word_is(line, wlen, "OFF"))
        cmd = C_OFF;
    else if (word_is(line, wlen, "STATE"))
        cmd = C_STATE;
    else if (word_is(line, wlen, "TIMEOUT"))
        cmd = C_TIMEOUT;
    else if (word_is(line, wlen, "PING"))
        cmd = C_PING;
    else
        return reply_err(out, PROTO_ERR_UNKNOWN_CMD); /* also the empty line */

    if (cmd == C_ON || cmd == C_TIMEOUT) {
        if (!arg || !parse_uint(arg, alen, &val))
            return reply_err(out, PROTO_ERR_BAD_ARG);
        if (cmd == C_ON && val >= PROTO_NUM_LEDS)
            return reply_err(out, PROTO_ERR_RANGE);
        if (cmd == C_TIMEOUT &&
            (val < PROTO_TIMEOUT_MIN_MS || val > PROTO_TIMEOUT_MAX_MS))
            return reply_err(out, PROTO_ERR_RANGE);
    } else if (arg) {
        /* Commands without an argument reject anything after the word,
         * including a lone trailing space. */
        return reply_err(out, PROTO_ERR_BAD_ARG);
    }

    /* Accepted: from here on the command succeeds. Any accepted command is
     * proof of a live host, so it restarts the silence clock. */
    p->silence_ms = 0;
    put_s(&w, "OK ");
    switch (cmd) {
    case C_ID:
        put_s(&w, "ID " PROTO_IDENT);
        break;
    case C_ON:
        p->led = (int8_t)val;
        p->tripped = 0;
        put_s(&w, "ON ");
        put_u(&w, val);
        break;
    case C_OFF:
        p->led = PROTO_LED_OFF;
        put_s(&w, "OFF");
        break;
    case C_STATE:
        put_s(&w, "STATE ");
        if (p->led == PROTO_LED_OFF)
            put_s(&w, "OFF");
        else
            put_u(&w, (uint16_t)p->led);
        put_s(&w, " timeout=");
        put_u(&w, p->timeout_ms);
        put_s(&w, p->tripped ? " tripped=1" : " tripped=0");
        break;
    case C_TIMEOUT:
        p->timeout_ms = val;
        put_s(&w, "TIMEOUT ");
        put_u(&w, val);
        break;
    case C_PING:
        put_s(&w, "PONG");
        break;
    }
    return finish(&w);
}

/* --- byte input --------------------------------------------------------- */

uint8_t proto_feed(proto_t *p, uint8_t byte, char *out)
{
    uint8_t n;

    if (byte == '\r')
        return 0; /* CR is dropped wherever it appears */

    if (byte != '\n') {
        if (p->too_long)
            return 0; /* discarding the rest of an overlong line */
        if (p->len >= PROTO_MAX_LINE) {
            p->too_long = 1;
            return 0;
        }
        if (byte < 0x20 || byte > 0x7e)
            p->bad_char = 1; /* control, DEL, NUL, >= 0x80: stored, refused */
        p->line[p->len++] = (char)byte;
        return 0;
    }

    /* End of line: exactly one answer. Priority: too long, bad byte, parse. */
    if (p->too_long)
        n = reply_err(out, PROTO_ERR_TOO_LONG);
    else if (p->bad_char)
        n = reply_err(out, PROTO_ERR_BAD_CHAR);
    else
        n = execute(p, out);

    p->len = 0;
    p->too_long = 0;
    p->bad_char = 0;
    return n;
}

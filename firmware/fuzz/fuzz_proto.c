/*
 * fuzz_proto.c - libFuzzer target for the protocol parser/state machine.
 *
 * Input layout: byte 0 = how many fed bytes between clock bursts (0: never),
 * byte 1 = burst length in ms, the rest = bytes as received on the
 * UART. Invariants checked after every byte and every tick:
 *  - the state is always valid: at most one LED (led in -1..9), timeout in
 *    100..60000, line length <= 32;
 *  - a byte other than '\n' produces no answer and changes no observable
 *    state; every '\n' produces exactly one answer: "OK ..." or "ERR ...",
 *    printable ASCII, one '\n' at the end, within PROTO_MAX_REPLY;
 *  - an ERR answer leaves the observable state untouched; OK answers agree
 *    with the state they report or set;
 *  - a tick only ever switches the LED off (and then sets tripped).
 * Build/run: make fuzz [FUZZ_SECONDS=n]
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"

#define REQUIRE(cond)                                                    \
    do {                                                                 \
        if (!(cond)) {                                                   \
            fprintf(stderr, "invariant failed: %s (line %d)\n", #cond, __LINE__); \
            abort();                                                     \
        }                                                                \
    } while (0)

typedef struct {
    int8_t led;
    uint8_t tripped;
    uint16_t timeout_ms;
    uint16_t silence_ms;
} observable_t;

static observable_t observe(const proto_t *p)
{
    observable_t o = {p->led, p->tripped, p->timeout_ms, p->silence_ms};
    return o;
}

static int same(observable_t a, observable_t b)
{
    return a.led == b.led && a.tripped == b.tripped && a.timeout_ms == b.timeout_ms &&
           a.silence_ms == b.silence_ms;
}

static void check_valid(const proto_t *p)
{
    REQUIRE(p->led >= PROTO_LED_OFF && p->led < PROTO_NUM_LEDS);
    REQUIRE(p->timeout_ms >= PROTO_TIMEOUT_MIN_MS && p->timeout_ms <= PROTO_TIMEOUT_MAX_MS);
    REQUIRE(p->len <= PROTO_MAX_LINE);
    REQUIRE(p->tripped <= 1 && p->too_long <= 1 && p->bad_char <= 1);
    REQUIRE(p->silence_ms <= p->timeout_ms + 1u);
}

static void check_answer(const proto_t *p, observable_t before, const char *r, uint8_t n)
{
    char text[PROTO_MAX_REPLY + 1];
    char want[64];

    REQUIRE(n >= 4 && n <= PROTO_MAX_REPLY);
    REQUIRE(r[n - 1] == '\n');
    for (uint8_t i = 0; i + 1 < n; i++)
        REQUIRE(r[i] >= 0x20 && r[i] <= 0x7e);
    memcpy(text, r, n - 1);
    text[n - 1] = 0;

    if (strncmp(text, "ERR ", 4) == 0) {
        REQUIRE(same(before, observe(p)));
        REQUIRE(text[4] >= '1' && text[4] <= '5' && text[5] == ' ');
        return;
    }
    REQUIRE(strncmp(text, "OK ", 3) == 0);
    REQUIRE(p->silence_ms == 0);
    if (strncmp(text, "OK ON ", 6) == 0) {
        REQUIRE(p->led >= 0 && !p->tripped);
        snprintf(want, sizeof want, "OK ON %d", p->led);
        REQUIRE(strcmp(text, want) == 0);
        REQUIRE(p->timeout_ms == before.timeout_ms);
    } else if (strcmp(text, "OK OFF") == 0) {
        REQUIRE(p->led == PROTO_LED_OFF && p->tripped == before.tripped);
    } else if (strncmp(text, "OK TIMEOUT ", 11) == 0) {
        snprintf(want, sizeof want, "OK TIMEOUT %u", p->timeout_ms);
        REQUIRE(strcmp(text, want) == 0);
        REQUIRE(p->led == before.led && p->tripped == before.tripped);
    } else if (strncmp(text, "OK STATE ", 9) == 0) {
        REQUIRE(p->led == before.led && p->tripped == before.tripped &&
                p->timeout_ms == before.timeout_ms);
        if (p->led == PROTO_LED_OFF)
            snprintf(want, sizeof want, "OK STATE OFF timeout=%u tripped=%u", p->timeout_ms, p->tripped);
        else
            snprintf(want, sizeof want, "OK STATE %d timeout=%u tripped=%u", p->led, p->timeout_ms,
                     p->tripped);
        REQUIRE(strcmp(text, want) == 0);
    } else {
        REQUIRE(strcmp(text, "OK PONG") == 0 ||
                strcmp(text, "OK ID " PROTO_IDENT) == 0);
        REQUIRE(p->led == before.led && p->tripped == before.tripped &&
                p->timeout_ms == before.timeout_ms);
    }
}

static void do_tick(proto_t *p)
{
    observable_t before = observe(p);
    uint8_t fired = proto_tick_ms(p);
    check_valid(p);
    REQUIRE(p->timeout_ms == before.timeout_ms);
    if (fired) {
        REQUIRE(before.led != PROTO_LED_OFF && p->led == PROTO_LED_OFF && p->tripped == 1);
    } else {
        REQUIRE(p->led == before.led && p->tripped == before.tripped);
    }
    if (p->silence_ms > p->timeout_ms)
        REQUIRE(p->led == PROTO_LED_OFF);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    proto_t p;
    unsigned every, burst_ms, since = 0;

    if (size < 2)
        return 0;
    every = data[0];
    burst_ms = data[1];
    data += 2;
    size -= 2;

    proto_init(&p);
    check_valid(&p);
    for (size_t i = 0; i < size; i++) {
        /* Guard bytes around the answer buffer catch any overrun, on top
         * of ASan's own redzones. */
        char guard_lo[8], reply[PROTO_MAX_REPLY], guard_hi[8];
        observable_t before = observe(&p);
        uint8_t n;

        memset(guard_lo, 0xA5, sizeof guard_lo);
        memset(guard_hi, 0x5A, sizeof guard_hi);
        n = proto_feed(&p, data[i], reply);
        for (unsigned k = 0; k < sizeof guard_lo; k++)
            REQUIRE((uint8_t)guard_lo[k] == 0xA5 && (uint8_t)guard_hi[k] == 0x5A);
        check_valid(&p);
        if (data[i] == '\n') {
            REQUIRE(n > 0);
            check_answer(&p, before, reply, n);
        } else {
            REQUIRE(n == 0);
            REQUIRE(same(before, observe(&p)));
        }
        if (every && ++since >= every) {
            since = 0;
            for (unsigned t = 0; t < burst_ms; t++)
                do_tick(&p);
        }
    }
    return 0;
}

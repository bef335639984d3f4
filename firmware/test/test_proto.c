/*
 * test_proto.c - native unit test of the protocol parser/state machine.
 * Built with the host compiler plus ASan/UBSan by `make test-native`.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"

static int failures;
static int checks;

#define CHECK(cond, ...)                                                   \
    do {                                                                   \
        checks++;                                                          \
        if (!(cond)) {                                                     \
            failures++;                                                    \
            fprintf(stderr, "%s:%d: CHECK(%s) failed: ", __FILE__, __LINE__, \
                    #cond);                                                \
            fprintf(stderr, __VA_ARGS__);                                  \
            fputc('\n', stderr);                                           \
        }                                                                  \
    } while (0)

/* Feed raw bytes; concatenate every answer into `out` (NUL terminated) and
 * return the number of answers. */
static int feed(proto_t *p, const char *bytes, size_t n, char *out, size_t cap)
{
    size_t used = 0;
    int answers = 0;
    out[0] = 0;
    for (size_t i = 0; i < n; i++) {
        char reply[PROTO_MAX_REPLY];
        uint8_t len = proto_feed(p, (uint8_t)bytes[i], reply);
        if (len) {
            answers++;
            if (used + len < cap) {
                memcpy(out + used, reply, len);
                used += len;
                out[used] = 0;
            }
        }
    }
    return answers;
}

/* Send one line (a '\n' is appended) and expect exactly `want` + "\n". */
static void expect_line(proto_t *p, const char *line, const char *want, int lineno)
{
    char buf[1024], got[256];
    size_t n = strlen(line);
    memcpy(buf, line, n);
    buf[n++] = '\n';
    int answers = feed(p, buf, n, got, sizeof got);
    char w[128];
    snprintf(w, sizeof w, "%s\n", want);
    checks++;
    if (answers != 1 || strcmp(got, w) != 0) {
        failures++;
        fprintf(stderr, "line %d: sent \"%s\": want \"%s\", got %d answer(s) \"%s\"\n",
                lineno, line, want, answers, got);
    }
}
#define EXPECT(p, line, want) expect_line(p, line, want, __LINE__)

/* Everything but the scratch line buffer. */
static int same_state(const proto_t *a, const proto_t *b)
{
    return a->led == b->led && a->tripped == b->tripped &&
           a->timeout_ms == b->timeout_ms && a->silence_ms == b->silence_ms &&
           a->len == b->len && a->too_long == b->too_long && a->bad_char == b->bad_char;
}

static void tick(proto_t *p, unsigned ms)
{
    while (ms--)
        proto_tick_ms(p);
}

static void test_power_up(void)
{
    proto_t p;
    proto_init(&p);
    CHECK(p.led == PROTO_LED_OFF, "led %d", p.led);
    CHECK(p.timeout_ms == 3000, "timeout %u", p.timeout_ms);
    CHECK(p.tripped == 0, "tripped");
    CHECK(strcmp(PROTO_BANNER, "READY psscan-led fw=1.0.0 proto=1 leds=10\n") == 0, "banner");
}

static void test_commands(void)
{
    proto_t p;
    proto_init(&p);
    EXPECT(&p, "ID", "OK ID psscan-led fw=1.0.0 proto=1 leds=10");
    EXPECT(&p, "PING", "OK PONG");
    EXPECT(&p, "STATE", "OK STATE OFF timeout=3000 tripped=0");
    for (int n = 0; n < 10; n++) {
        char cmd[24], want[32];
        snprintf(cmd, sizeof cmd, "ON %d", n);
        snprintf(want, sizeof want, "OK ON %d", n);
        EXPECT(&p, cmd, want);
        CHECK(p.led == n, "ON %d -> led %d", n, p.led);
    }
    EXPECT(&p, "ON 3", "OK ON 3");
    EXPECT(&p, "ON 7", "OK ON 7");
    CHECK(p.led == 7, "led %d", p.led);
    EXPECT(&p, "STATE", "OK STATE 7 timeout=3000 tripped=0");
    EXPECT(&p, "OFF", "OK OFF");
    CHECK(p.led == PROTO_LED_OFF, "led %d", p.led);
    EXPECT(&p, "OFF", "OK OFF"); /* idempotent */
    EXPECT(&p, "TIMEOUT 100", "OK TIMEOUT 100");
    EXPECT(&p, "TIMEOUT 60000", "OK TIMEOUT 60000");
    EXPECT(&p, "TIMEOUT 0500", "OK TIMEOUT 500"); /* leading zero ok */
    EXPECT(&p, "ON 09", "OK ON 9");
    EXPECT(&p, "STATE", "OK STATE 9 timeout=500 tripped=0");
    /* CR is dropped anywhere, so CRLF lines work. */
    EXPECT(&p, "PING\r", "OK PONG");
    EXPECT(&p, "ST\rATE\r", "OK STATE 9 timeout=500 tripped=0");
}

static void test_errors_change_nothing(void)
{
    proto_t p, before;
    proto_init(&p);
    EXPECT(&p, "TIMEOUT 1234", "OK TIMEOUT 1234");
    EXPECT(&p, "ON 5", "OK ON 5");
    tick(&p, 100);
    before = p;

    static const struct {
        const char *line;
        const char *want;
    } cases[] = {
        {"", "ERR 1 unknown command"},
        {"on 3", "ERR 1 unknown command"},
        {"On 3", "ERR 1 unknown command"},
        {" ON 3", "ERR 1 unknown command"},
        {"ONN 3", "ERR 1 unknown command"},
        {"HELLO", "ERR 1 unknown command"},
        {"ON", "ERR 2 bad argument"},
        {"ON ", "ERR 2 bad argument"},
        {"ON  3", "ERR 2 bad argument"},
        {"ON 3 ", "ERR 2 bad argument"},
        {"ON -1", "ERR 2 bad argument"},
        {"ON +1", "ERR 2 bad argument"},
        {"ON 3x", "ERR 2 bad argument"},
        {"ON x", "ERR 2 bad argument"},
        {"OFF ", "ERR 2 bad argument"},
        {"OFF 1", "ERR 2 bad argument"},
        {"ID x", "ERR 2 bad argument"},
        {"PING 1", "ERR 2 bad argument"},
        {"STATE now", "ERR 2 bad argument"},
        {"TIMEOUT", "ERR 2 bad argument"},
        {"TIMEOUT 1e3", "ERR 2 bad argument"},
        {"ON 10", "ERR 4 out of range"},
        {"ON 99999999999", "ERR 4 out of range"},
        {"TIMEOUT 99", "ERR 4 out of range"},
        {"TIMEOUT 0", "ERR 4 out of range"},
        {"TIMEOUT 60001", "ERR 4 out of range"},
        {"TIMEOUT 65536", "ERR 4 out of range"},
        {"TIMEOUT 4294967396", "ERR 4 out of range"},
        {"ON\t3", "ERR 5 bad character"},
        {"ON 3\x7f", "ERR 5 bad character"},
        {"\x80ON 3", "ERR 5 bad character"},
        {"ON \xff", "ERR 5 bad character"},
        {"\x1b[A", "ERR 5 bad character"},
    };
    for (size_t i = 0; i < sizeof cases / sizeof cases[0]; i++) {
        EXPECT(&p, cases[i].line, cases[i].want);
        CHECK(same_state(&p, &before), "state changed by \"%s\"", cases[i].line);
    }

    /* NUL inside a line (can't go through a C string). */
    {
        char got[128];
        int n = feed(&p, "ON 2\0\n", 6, got, sizeof got);
        CHECK(n == 1 && strcmp(got, "ERR 5 bad character\n") == 0, "NUL: %d \"%s\"", n, got);
        CHECK(same_state(&p, &before), "state changed by NUL line");
    }
}

static void test_line_length(void)
{
    proto_t p;
    char line[600], got[256];
    proto_init(&p);

    /* exactly 32 characters: accepted */
    snprintf(line, sizeof line, "TIMEOUT %s", "000000000000000000001000");
    CHECK(strlen(line) == PROTO_MAX_LINE, "len %zu", strlen(line));
    EXPECT(&p, line, "OK TIMEOUT 1000");

    /* 33 characters: rejected, once */
    snprintf(line, sizeof line, "TIMEOUT %s", "0000000000000000000001000");
    EXPECT(&p, line, "ERR 3 line too long");
    CHECK(p.timeout_ms == 1000, "timeout %u", p.timeout_ms);

    /* CRs do not count towards the length */
    {
        char buf[64];
        int n = snprintf(buf, sizeof buf, "TIMEOUT %s\r\r\r\n", "000000000000000000002000");
        n = feed(&p, buf, (size_t)n, got, sizeof got);
        CHECK(n == 1 && strcmp(got, "OK TIMEOUT 2000\n") == 0, "%d \"%s\"", n, got);
    }

    /* 500 bytes (with garbage and a valid command hidden at the end):
     * one ERR 3, nothing executed, next line parsed normally. */
    {
        char big[520];
        for (int i = 0; i < 500; i++)
            big[i] = (char)(i % 7 == 0 ? 0xff : 'A' + i % 26);
        memcpy(big + 500, "ON 1\nPING\n", 10);
        int n = feed(&p, big, 510, got, sizeof got);
        CHECK(n == 2 && strcmp(got, "ERR 3 line too long\nOK PONG\n") == 0, "%d \"%s\"", n, got);
        CHECK(p.led == PROTO_LED_OFF, "led %d", p.led);
    }

    /* Several lines in one burst: one answer each, in order. */
    {
        const char burst[] = "ID\nON 4\n\nSTATE\nOFF\n";
        int n = feed(&p, burst, sizeof burst - 1, got, sizeof got);
        CHECK(n == 5, "answers %d", n);
        CHECK(strcmp(got, "OK ID psscan-led fw=1.0.0 proto=1 leds=10\nOK ON 4\n"
                          "ERR 1 unknown command\nOK STATE 4 timeout=2000 tripped=0\nOK OFF\n") == 0,
              "\"%s\"", got);
    }
}

static void test_silence_timeout(void)
{
    proto_t p;
    proto_init(&p);

    /* Default 3000 ms: on at 3000 ms of silence, off after 3001. */
    EXPECT(&p, "ON 2", "OK ON 2");
    tick(&p, 3000);
    CHECK(p.led == 2 && !p.tripped, "led %d tripped %d", p.led, p.tripped);
    CHECK(proto_tick_ms(&p) == 1, "trip tick");
    CHECK(p.led == PROTO_LED_OFF && p.tripped, "led %d tripped %d", p.led, p.tripped);
    CHECK(proto_tick_ms(&p) == 0, "trips once");
    EXPECT(&p, "STATE", "OK STATE OFF timeout=3000 tripped=1");
    EXPECT(&p, "PING", "OK PONG");
    EXPECT(&p, "OFF", "OK OFF");
    EXPECT(&p, "STATE", "OK STATE OFF timeout=3000 tripped=1"); /* only ON clears */
    EXPECT(&p, "ON 1", "OK ON 1");
    EXPECT(&p, "STATE", "OK STATE 1 timeout=3000 tripped=0");

    /* Keepalive: any accepted command restarts the clock. */
    EXPECT(&p, "TIMEOUT 100", "OK TIMEOUT 100");
    for (int i = 0; i < 50; i++) {
        tick(&p, 90);
        EXPECT(&p, "PING", "OK PONG");
    }
    CHECK(p.led == 1 && !p.tripped, "keepalive failed: led %d", p.led);

    /* Rejected lines are not a keepalive. */
    for (int i = 0; i < 3; i++) {
        tick(&p, 40);
        EXPECT(&p, "NOPE", "ERR 1 unknown command");
    }
    CHECK(p.led == PROTO_LED_OFF && p.tripped, "garbage kept LED on: led %d", p.led);

    /* Timeout with the LEDs already off does not set tripped. */
    EXPECT(&p, "ON 0", "OK ON 0");
    EXPECT(&p, "OFF", "OK OFF");
    tick(&p, 500);
    EXPECT(&p, "STATE", "OK STATE OFF timeout=100 tripped=0");

    /* A very long silence neither wraps nor re-arms anything. */
    EXPECT(&p, "TIMEOUT 60000", "OK TIMEOUT 60000");
    EXPECT(&p, "ON 8", "OK ON 8");
    tick(&p, 200000);
    CHECK(p.led == PROTO_LED_OFF && p.tripped && p.silence_ms == 60001, "silence %u", p.silence_ms);
}

int main(void)
{
    test_power_up();
    test_commands();
    test_errors_change_nothing();
    test_line_length();
    test_silence_timeout();
    if (failures) {
        fprintf(stderr, "test_proto: %d of %d checks FAILED\n", failures, checks);
        return 1;
    }
    printf("test_proto: all %d checks passed\n", checks);
    return 0;
}

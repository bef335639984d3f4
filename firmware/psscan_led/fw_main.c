/*
 * fw_main.c - psscan LED controller firmware, hardware layer (ATmega328P).
 *
 * Owns the pins, USART0 (115200 8N1, interrupt driven RX and TX rings),
 * Timer0 (1 kHz tick) and the watchdog. All protocol decisions live in
 * proto.c; this file feeds it bytes and ticks and drives the LED pins from
 * proto.led.
 *
 * Pin map (Arduino Uno/Nano):  LED 0..5 = D2..D7  = PD2..PD7
 *                              LED 6..9 = D8..D11 = PB0..PB3
 *                              status   = D13     = PB5 (heartbeat)
 * A pin driven high switches its LED channel on (N-MOSFET gate).
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <util/atomic.h>

#include "fw_main.h"
#include "proto.h"

#if !defined(F_CPU)
#define F_CPU 16000000UL
#endif
#if F_CPU != 16000000UL
#error "timer and baud settings below assume a 16 MHz clock"
#endif

#define LED_D_MASK 0xFCu /* PD2..PD7: LED 0..5 */
#define LED_B_MASK 0x0Fu /* PB0..PB3: LED 6..9 */
#define STATUS_BIT _BV(PB5)

/* --- earliest possible "all off" ---------------------------------------- */

/*
 * Runs from .init3: after the stack is set up but before .data/.bss are
 * initialised and before main(), i.e. the first thing the firmware does.
 * After any reset the pins are already high-impedance inputs (the gate
 * pull-downs keep the MOSFETs off); here we actively drive them low.
 * It also clears the watchdog: after a watchdog reset the WDT stays enabled
 * at its shortest period and would otherwise reset us again before main().
 */
void fw_early_init(void) __attribute__((naked, used, section(".init3")));
void fw_early_init(void)
{
    PORTD &= (uint8_t)~LED_D_MASK;
    DDRD |= LED_D_MASK;
    PORTB &= (uint8_t)~(LED_B_MASK | STATUS_BIT);
    DDRB |= LED_B_MASK | STATUS_BIT;
    MCUSR = 0;
    wdt_disable();
}

/* --- LEDs --------------------------------------------------------------- */

/* Drive exactly the LED `led` (or none for PROTO_LED_OFF). */
static void leds_apply(int8_t led)
{
    uint8_t d = 0, b = 0;
    if (led >= 0 && led <= 5)
        d = (uint8_t)(1u << (led + 2));
    else if (led >= 6 && led <= 9)
        b = (uint8_t)(1u << (led - 6));
    /* Switch the old LED off before the new one on, so two channels are
     * never on together, not even for one instruction. */
    PORTD &= (uint8_t)~(LED_D_MASK & (uint8_t)~d);
    PORTB &= (uint8_t)~(LED_B_MASK & (uint8_t)~b);
    PORTD |= d;
    PORTB |= b;
}

/* --- USART0 ------------------------------------------------------------- */

#define RX_SIZE 128u /* powers of two: indices wrap with a mask */
#define TX_SIZE 128u
/* Byte stored in place of received data that was damaged (framing, parity,
 * overrun) or lost to a full ring: >= 0x80, so the line is answered ERR 5. */
#define RX_DAMAGED 0xFFu

static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head, rx_tail, rx_lost;
static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail;

static void uart_init(void)
{
    /* 115200 baud: U2X with UBRR=16 gives 117647 baud (+2.1%), the same
     * setting the Arduino core uses; well inside what USB-serial bridges
     * accept. */
    UCSR0A = _BV(U2X0);
    UBRR0 = 16;
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

ISR(USART_RX_vect)
{
    uint8_t status = UCSR0A; /* must be read before UDR0 */
    uint8_t c = UDR0;
    uint8_t next = (uint8_t)((rx_head + 1u) & (RX_SIZE - 1u));

    if (status & (_BV(FE0) | _BV(DOR0) | _BV(UPE0)))
        c = RX_DAMAGED;
    if (rx_lost) {
        /* Earlier bytes were dropped: mark the gap first so the line they
         * belonged to is refused instead of silently shortened. */
        if (next == rx_tail)
            return;
        rx_buf[rx_head] = RX_DAMAGED;
        rx_head = next;
        rx_lost = 0;
        next = (uint8_t)((rx_head + 1u) & (RX_SIZE - 1u));
    }
    if (next == rx_tail) {
        rx_lost = 1;
        return;
    }
    rx_buf[rx_head] = c;
    rx_head = next;
}

static int16_t rx_pop(void)
{
    uint8_t c;
    if (rx_tail == rx_head)
        return -1;
    c = rx_buf[rx_tail];
    rx_tail = (uint8_t)((rx_tail + 1u) & (RX_SIZE - 1u));
    return c;
}

ISR(USART_UDRE_vect)
{
    if (tx_tail == tx_head) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0); /* ring empty: stop */
        return;
    }
    UDR0 = tx_buf[tx_tail];
    tx_tail = (uint8_t)((tx_tail + 1u) & (TX_SIZE - 1u));
}

static void tx_write(const char *s, uint8_t n)
{
    while (n--) {
        uint8_t next = (uint8_t)((tx_head + 1u) & (TX_SIZE - 1u));
        /* Ring full: wait for the UDRE interrupt to make room. Only happens
         * if the host pipelines many commands without reading answers. */
        while (next == tx_tail) {
            wdt_reset();
            sleep_mode();
        }
        tx_buf[tx_head] = (uint8_t)*s++;
        tx_head = next;
        UCSR0B |= _BV(UDRIE0);
    }
}

/* --- 1 ms tick ---------------------------------------------------------- */

static volatile uint8_t ms_pending;

static void timer_init(void)
{
    /* Timer0 CTC: 16 MHz / 64 / 250 = 1000 Hz. */
    TCCR0A = _BV(WGM01);
    TCCR0B = _BV(CS01) | _BV(CS00);
    OCR0A = 249; /* after the mode bits: simavr checks the mode on this write */
    TIMSK0 = _BV(OCIE0A);
}

ISR(TIMER0_COMPA_vect)
{
    if (ms_pending != 0xFF)
        ms_pending++;
}

/* --- main loop ---------------------------------------------------------- */

void fw_main(void)
{
    static proto_t proto; /* static: keeps it out of the stack budget */
    char reply[PROTO_MAX_REPLY];
    int8_t applied = PROTO_LED_OFF;
    uint16_t heartbeat_ms = 0;

    proto_init(&proto);
    leds_apply(PROTO_LED_OFF);
    uart_init();
    timer_init();
    set_sleep_mode(SLEEP_MODE_IDLE); /* USART and Timer0 keep running */
    /* The main loop runs at least once per ms (timer tick), so a quarter
     * second without wdt_reset() means the MCU is hung: reset, which turns
     * the LEDs off in fw_early_init(). */
    wdt_enable(WDTO_250MS);
    sei();

    tx_write(PROTO_BANNER, (uint8_t)(sizeof PROTO_BANNER - 1));

    for (;;) {
        int16_t c;
        uint8_t ticks;

        wdt_reset();

        /* No effect on hardware. In simavr, reading UCSR0A with an empty
         * receive FIFO is what signals "XON" to the pty bridge; an
         * interrupt-only receiver would otherwise never get input. */
        (void)UCSR0A;

        while ((c = rx_pop()) >= 0) {
            uint8_t n;
#ifdef PSSCAN_TEST_HANG
            /* Test builds only (make test-sim): a BEL byte hangs the MCU so
             * the watchdog path can be exercised in the simulator. */
            if (c == 0x07)
                for (;;) {
                }
#endif
            n = proto_feed(&proto, (uint8_t)c, reply);
            /* Pins first, answer second: when the host reads "OK ON n"
             * the LED is already on. */
            if (proto.led != applied) {
                leds_apply(proto.led);
                applied = proto.led;
            }
            if (n)
                tx_write(reply, n);
        }

        ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
        {
            ticks = ms_pending;
            ms_pending = 0;
        }
        while (ticks--) {
            proto_tick_ms(&proto);
            if (proto.led != applied) {
                leds_apply(proto.led);
                applied = proto.led;
            }
            /* Status LED: 1 Hz blink normally, 4 Hz after a silence trip. */
            if (++heartbeat_ms >= (proto.tripped ? 125u : 500u)) {
                heartbeat_ms = 0;
                PINB = STATUS_BIT; /* writing PINx toggles PORTx */
            }
        }

        /* Sleep until the next interrupt unless work arrived meanwhile.
         * sei; sleep is race free: the instruction after sei runs before
         * any interrupt is taken. */
        cli();
        if (rx_tail == rx_head && ms_pending == 0) {
            sleep_enable();
            sei();
            sleep_cpu();
            sleep_disable();
        }
        sei();
    }
}

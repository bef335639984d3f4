/*
 * psscan-avr-sim - run the psscan LED firmware in simavr, in real time.
 *
 *   psscan-avr-sim --firmware build/psscan_led.elf [--pin-log FILE]
 *                  [--speed realtime|max] [--mcu atmega328p] [--freq 16000000]
 *                  [--exit-with-parent]
 *
 * - Loads the ELF into a simulated ATmega328P at 16 MHz.
 * - Bridges USART0 to a fresh pseudo-terminal with simavr's uart_pty part and
 *   prints exactly one line on stdout, "PTY /dev/pts/N", then nothing else
 *   there (all simavr chatter goes to stderr). Open that path like a serial
 *   port. uart_pty also points /tmp/simavr-uart0 at its pty; with several
 *   instances that link is meaningless, use the printed path.
 * - Throttles the simulation so simulated time never runs ahead of wall time
 *   (by more than ~0.1 ms), so the firmware's millisecond timeouts are wall
 *   milliseconds. --speed max disables the throttle.
 * - Writes every level change of the 10 LED pins to the pin log, one flushed
 *   line each (format in ../PROTOCOL.md, "Simulator pin log").
 * - Runs until SIGTERM/SIGINT/SIGHUP (exit 0) or until the simulated MCU
 *   crashes or stops for good (exit 2). Bad usage or load errors: exit 1.
 *   --exit-with-parent: also get SIGTERM when the thread that started us
 *   exits (Linux PR_SET_PDEATHSIG), so killed test runs leave no orphans.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <inttypes.h>
#include <pthread.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <avr_extint.h>
#include <avr_ioport.h>
#include <avr_uart.h>
#include <sim_avr.h>
#include <sim_elf.h>
#include <sim_irq.h>
#include <uart_pty.h>

#define NUM_LEDS 10

/* LED n -> (port, bit); must match fw_main.c. */
static const struct {
    char port;
    uint8_t bit;
} led_pins[NUM_LEDS] = {
    {'D', 2}, {'D', 3}, {'D', 4}, {'D', 5}, {'D', 6},
    {'D', 7}, {'B', 0}, {'B', 1}, {'B', 2}, {'B', 3},
};

static avr_t *avr;
static uart_pty_t pty;
static FILE *pin_log;
static int realtime = 1;
static struct timespec wall_start;
static volatile sig_atomic_t stop_signal;

/* Monotonic simulated cycle count: simavr may restart avr->cycle at a
 * (watchdog) reset, so wrap-arounds are folded into a base. */
static uint64_t cycle_base, cycle_last;
static int8_t led_level[NUM_LEDS];
static uint64_t max_lag_ns;

static uint64_t total_cycles(void)
{
    if (avr->cycle < cycle_last)
        cycle_base += cycle_last;
    cycle_last = avr->cycle;
    return cycle_base + avr->cycle;
}

static uint64_t cycles_to_ns(uint64_t c)
{
    uint64_t f = avr->frequency;
    return c / f * 1000000000ull + c % f * 1000000000ull / f;
}

static uint64_t wall_ns(void)
{
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (uint64_t)(now.tv_sec - wall_start.tv_sec) * 1000000000ull +
           (uint64_t)now.tv_nsec - (uint64_t)wall_start.tv_nsec;
}

/* Block until wall time has caught up with simulated cycle `target`. */
static void throttle_to(uint64_t target)
{
    uint64_t sim, now;
    struct timespec until;

    if (!realtime)
        return;
    sim = cycles_to_ns(target);
    now = wall_ns();
    if (now >= sim) {
        if (now - sim > max_lag_ns)
            max_lag_ns = now - sim;
        return;
    }
    sim += (uint64_t)wall_start.tv_nsec;
    until.tv_sec = wall_start.tv_sec + (time_t)(sim / 1000000000ull);
    until.tv_nsec = (long)(sim % 1000000000ull);
    /* An interrupting signal just ends the wait early; the main loop then
     * sees stop_signal. */
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &until, NULL);
}

/*
 * simavr calls this when the core sleeps (SLEEP instruction) with the number
 * of cycles until the next timer event, then adds them to avr->cycle in one
 * jump. Waiting here keeps the jump from running ahead of the wall clock.
 */
static void sim_sleep(avr_t *a, avr_cycle_count_t how_long)
{
    (void)a;
    throttle_to(total_cycles() + how_long);
}

/* --- pin log -------------------------------------------------------------- */

static void log_line(int led, int level)
{
    if (!pin_log)
        return;
    fprintf(pin_log, "sim_us=%" PRIu64 " wall_us=%" PRIu64 " led=%d level=%d\n",
            cycles_to_ns(total_cycles()) / 1000u, wall_ns() / 1000u, led, level);
    fflush(pin_log);
}

static void log_comment(const char *what)
{
    if (!pin_log)
        return;
    fprintf(pin_log, "# %s sim_us=%" PRIu64 " wall_us=%" PRIu64 "\n", what,
            cycles_to_ns(total_cycles()) / 1000u, wall_ns() / 1000u);
    fflush(pin_log);
}

/* After power-up or any reset every pin is a high-impedance input: off. */
static void log_all_off(const char *why)
{
    log_comment(why);
    for (int i = 0; i < NUM_LEDS; i++) {
        led_level[i] = 0;
        log_line(i, 0);
    }
}

/* Level of an LED pin = driven high = PORT bit and DDR bit both set. Called
 * on any port/direction change; logs only actual changes. */
static void rescan_pins(void)
{
    avr_ioport_state_t b, d;
    if (avr_ioctl(avr, AVR_IOCTL_IOPORT_GETSTATE('B'), &b) ||
        avr_ioctl(avr, AVR_IOCTL_IOPORT_GETSTATE('D'), &d))
        return;
    for (int i = 0; i < NUM_LEDS; i++) {
        const avr_ioport_state_t *s = led_pins[i].port == 'B' ? &b : &d;
        int level = ((s->port & s->ddr) >> led_pins[i].bit) & 1;
        if (level != led_level[i]) {
            led_level[i] = (int8_t)level;
            log_line(i, level);
        }
    }
}

static void pin_irq_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    (void)param;
    rescan_pins();
}

static void watch_port(char name)
{
    /* PIN_ALL is raised after every PORT/DDR/PIN write (filtered to real
     * changes); the per-pin and register IRQs are extra triggers in case a
     * simavr version orders them differently. rescan_pins() dedups. */
    static const int irqs[] = {IOPORT_IRQ_PIN_ALL, IOPORT_IRQ_REG_PORT,
                               IOPORT_IRQ_DIRECTION_ALL, IOPORT_IRQ_PIN0,
                               IOPORT_IRQ_PIN1, IOPORT_IRQ_PIN2,
                               IOPORT_IRQ_PIN3, IOPORT_IRQ_PIN4,
                               IOPORT_IRQ_PIN5, IOPORT_IRQ_PIN6,
                               IOPORT_IRQ_PIN7};
    for (size_t i = 0; i < sizeof irqs / sizeof irqs[0]; i++) {
        avr_irq_t *irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(name), irqs[i]);
        if (irq)
            avr_irq_register_notify(irq, pin_irq_hook, NULL);
    }
}

/*
 * INT0/INT1 sit on PD2/PD3 (LEDs 0 and 1). With EICRA at its reset value
 * (low-level trigger) simavr polls a low pin on every single cycle, even with
 * the interrupt disabled, which made the simulation ~100x slower than needed.
 * The firmware never uses INT0/INT1, so turn that polling off. simavr turns
 * it back on in every reset, after our reset hook has run, so the hook only
 * flags it and the main loop reapplies it before the next instruction.
 */
static int extint_fix_pending = 1;

static void extint_fix(void)
{
    avr_extint_set_strict_lvl_trig(avr, 0, 0);
    avr_extint_set_strict_lvl_trig(avr, 1, 0);
    extint_fix_pending = 0;
}

static void (*core_reset)(struct avr_t *);

static void on_reset(struct avr_t *a)
{
    if (core_reset)
        core_reset(a);
    extint_fix_pending = 1;
    log_all_off("reset");
}

/* --- misc ----------------------------------------------------------------- */

static void on_signal(int sig)
{
    stop_signal = sig;
}

/* simavr's default logger writes to stdout; stdout is reserved for the PTY
 * line, so everything goes to stderr. */
static void sim_logger(avr_t *a, const int level, const char *fmt, va_list ap)
{
    if (!a || a->log >= level)
        vfprintf(stderr, fmt, ap);
}

static void usage(FILE *to)
{
    fprintf(to,
            "usage: psscan-avr-sim --firmware FILE.elf [--pin-log FILE]\n"
            "                      [--speed realtime|max] [--mcu NAME] [--freq HZ]\n"
            "                      [--exit-with-parent]\n"
            "Prints \"PTY /dev/pts/N\" on stdout, then runs until SIGTERM/SIGINT.\n");
}

static int set_raw(const char *path)
{
    struct termios tio;
    int fd = open(path, O_RDWR | O_NOCTTY);
    if (fd < 0)
        return -1;
    if (tcgetattr(fd, &tio) == 0) {
        cfmakeraw(&tio);
        cfsetispeed(&tio, B115200);
        cfsetospeed(&tio, B115200);
        tio.c_cc[VMIN] = 1;
        tio.c_cc[VTIME] = 0;
        tcsetattr(fd, TCSANOW, &tio);
    }
    return fd;
}

int main(int argc, char **argv)
{
    const char *fw_path = NULL, *log_path = NULL, *mcu = "atmega328p";
    uint32_t freq = 16000000;
    elf_firmware_t fw;
    int real_stdout, keep_slave, rc = 0;
    sigset_t sigs;
    struct sigaction sa;

    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) {
            usage(stdout);
            return 0;
        } else if (!strcmp(a, "--firmware") && v) {
            fw_path = v;
            i++;
        } else if (!strcmp(a, "--pin-log") && v) {
            log_path = v;
            i++;
        } else if (!strcmp(a, "--speed") && v) {
            if (!strcmp(v, "realtime"))
                realtime = 1;
            else if (!strcmp(v, "max"))
                realtime = 0;
            else {
                usage(stderr);
                return 1;
            }
            i++;
        } else if (!strcmp(a, "--exit-with-parent")) {
            pid_t parent = getppid();
            if (prctl(PR_SET_PDEATHSIG, SIGTERM) != 0 || getppid() != parent)
                return 1; /* parent already gone */
        } else if (!strcmp(a, "--mcu") && v) {
            mcu = v;
            i++;
        } else if (!strcmp(a, "--freq") && v) {
            freq = (uint32_t)strtoul(v, NULL, 10);
            i++;
        } else {
            usage(stderr);
            return 1;
        }
    }
    if (!fw_path || freq == 0) {
        usage(stderr);
        return 1;
    }

    /* From here until the PTY line, anything printed to stdout (simavr and
     * uart_pty use printf) is diverted to stderr. */
    fflush(stdout);
    real_stdout = dup(STDOUT_FILENO);
    dup2(STDERR_FILENO, STDOUT_FILENO);
    avr_global_logger_set(sim_logger);

    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(fw_path, &fw) != 0) {
        fprintf(stderr, "psscan-avr-sim: cannot load %s\n", fw_path);
        return 1;
    }
    snprintf(fw.mmcu, sizeof fw.mmcu, "%s", mcu);
    fw.frequency = freq;
    avr = avr_make_mcu_by_name(mcu);
    if (!avr) {
        fprintf(stderr, "psscan-avr-sim: unknown MCU %s\n", mcu);
        return 1;
    }
    avr_init(avr);
    avr->log = LOG_WARNING;
    avr_load_firmware(avr, &fw);
    avr->frequency = freq;
    avr->sleep = sim_sleep;
    core_reset = avr->reset;
    avr->reset = on_reset;

    if (log_path) {
        pin_log = fopen(log_path, "w");
        if (!pin_log) {
            fprintf(stderr, "psscan-avr-sim: %s: %s\n", log_path, strerror(errno));
            return 1;
        }
    }

    /* The pty thread must not take our termination signals: an interrupted
     * select() would end it. It inherits this mask; main unblocks below. */
    sigemptyset(&sigs);
    sigaddset(&sigs, SIGTERM);
    sigaddset(&sigs, SIGINT);
    sigaddset(&sigs, SIGHUP);
    pthread_sigmask(SIG_BLOCK, &sigs, NULL);

    /* Exactly one pty, no xterm, whatever the environment says. */
    unsetenv("SIMAVR_UART_TAP");
    unsetenv("SIMAVR_UART_XTERM");
    uart_pty_init(avr, &pty);
    if (!pty.pty.s) {
        fprintf(stderr, "psscan-avr-sim: cannot create a pty\n");
        return 1;
    }
    uart_pty_connect(&pty, '0');
    {
        /* No console echo of UART lines, and no usleep() on every UCSR0A
         * poll (simavr's default), which would break real-time pacing. */
        uint32_t flags = 0;
        avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
        flags &= ~(uint32_t)(AVR_UART_FLAG_POOL_SLEEP | AVR_UART_FLAG_STDIO);
        avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    }
    /* Put the slave side in raw mode before the firmware sends anything:
     * with the default cooked/echo settings the READY banner would be echoed
     * straight back into the firmware. Keeping this descriptor open also
     * keeps the settings and any unread output when the host closes and
     * reopens the port. */
    keep_slave = set_raw(pty.pty.slavename);
    if (keep_slave < 0) {
        fprintf(stderr, "psscan-avr-sim: %s: %s\n", pty.pty.slavename, strerror(errno));
        return 1;
    }

    watch_port('B');
    watch_port('D');

    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal; /* no SA_RESTART: wake clock_nanosleep */
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGHUP, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
    pthread_sigmask(SIG_UNBLOCK, &sigs, NULL);

    clock_gettime(CLOCK_MONOTONIC, &wall_start);
    if (pin_log) {
        struct timespec rt;
        clock_gettime(CLOCK_REALTIME, &rt);
        fprintf(pin_log,
                "# psscan-avr-sim pinlog v1 mcu=%s f_cpu=%" PRIu32
                " start_unix_us=%" PRIu64
                " leds=0:PD2,1:PD3,2:PD4,3:PD5,4:PD6,5:PD7,6:PB0,7:PB1,8:PB2,9:PB3\n",
                mcu, freq, (uint64_t)rt.tv_sec * 1000000u + (uint64_t)rt.tv_nsec / 1000u);
    }
    log_all_off("power-on");

    fflush(stdout);
    dprintf(real_stdout, "PTY %s\n", pty.pty.slavename);
    close(real_stdout); /* nothing else will ever be written there */

    {
        /* Busy stretches are checked every 0.1 ms of simulated time. */
        const uint64_t check_every = freq / 10000u ? freq / 10000u : 1u;
        uint64_t next_check = 0;

        while (!stop_signal) {
            int state;
            uint64_t now;
            if (extint_fix_pending)
                extint_fix();
            state = avr_run(avr);
            if (state == cpu_Done || state == cpu_Crashed) {
                fprintf(stderr, "psscan-avr-sim: firmware %s at pc=0x%04x\n",
                        state == cpu_Crashed ? "crashed" : "stopped (sleep with interrupts off?)",
                        (unsigned)avr->pc);
                log_comment(state == cpu_Crashed ? "crashed" : "stopped");
                rc = 2;
                break;
            }
            now = total_cycles();
            if (now >= next_check) {
                throttle_to(now);
                next_check = now + check_every;
            }
        }
    }

    {
        uint64_t sim = cycles_to_ns(total_cycles()), wall = wall_ns();
        if (!rc)
            log_comment("exit");
        fprintf(stderr,
                "psscan-avr-sim: exit sim=%.6fs wall=%.6fs max_lag_us=%" PRIu64 "\n",
                (double)sim / 1e9, (double)wall / 1e9, max_lag_ns / 1000u);
    }
    if (pin_log)
        fclose(pin_log);
    close(keep_slave);
    return rc;
}

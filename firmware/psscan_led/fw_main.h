/*
 * fw_main.h - psscan LED controller firmware entry point (ATmega328P).
 *
 * psscan_led.ino defines main() and calls fw_main(); defining main() in the
 * sketch keeps the Arduino core's main(), init() and Timer0 code out of the
 * image, so the firmware is the same whether built by the IDE or `make`.
 */
#ifndef PSSCAN_FW_MAIN_H
#define PSSCAN_FW_MAIN_H

#ifdef __cplusplus
extern "C" {
#endif

/* Never returns. */
void fw_main(void) __attribute__((noreturn));

#ifdef __cplusplus
}
#endif

#endif /* PSSCAN_FW_MAIN_H */

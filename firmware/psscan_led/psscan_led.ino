/*
 * psscan_led.ino - Arduino IDE wrapper for the psscan LED controller.
 *
 * The firmware is plain avr-libc C (fw_main.c, proto.c in this folder). This
 * sketch only provides main(): a sketch that defines main() replaces the
 * Arduino core's, so setup()/loop(), init(), millis() and HardwareSerial are
 * not linked in. Board: Arduino Uno or Nano (ATmega328P, 16 MHz).
 * Build from the command line instead with `make` in the firmware/ folder.
 */
#include "fw_main.h"

int main(void)
{
    fw_main();
}

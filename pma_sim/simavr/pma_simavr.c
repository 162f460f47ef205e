/*
 * pma_simavr: the firmware's own AVR image on a simulated ATmega2560, wired to a controller.
 *
 * simavr (Debian: libsimavr-dev) runs the unmodified .elf at 16 MHz, cycle by cycle: the
 * Arduino core's timers, interrupts, ADC, pulseInLong's micros() and the UART at its baud
 * rate. This program owns only the board's wiring and never reads a clock: it runs the AVR
 * for as many cycles as it is told and asks its controller (pma_sim.simavr_arduino, which
 * keeps the rig's physics and the USB-serial pty in the same simulated time) whenever the
 * firmware samples the world. docs/hardware.md ("Firmware in the loop") describes the whole.
 *
 * Protocol: text lines, the controller on stdin, this program's answers on stdout; every
 * time is in AVR cycles since the last reset.
 *   controller -> simulator             simulator -> controller
 *   run CYCLE    run up to CYCLE        done CYCLE           (after run, and after reset)
 *   rx HEX       bytes to UART0 RX      tx HEX               bytes the firmware sent (UART0)
 *   reset        power-on reset         valves CYCLE IN EX   valve pin levels changed
 *   stats        counters, see below    adc CYCLE            a conversion of the sensor's
 *                                                           channel starts: answer `MV`
 *                                       trig CYCLE           a valid trigger pulse ended:
 *                                                           answer the echo width in us
 *                                                           (0: no echo)
 *                                       stats KEY=VALUE ...
 *                                       error TEXT           the AVR stopped (exit 3)
 * End of stdin ends the program (exit 0). Stop signals are left to the controller.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <getopt.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <unistd.h>

#include "avr_adc.h"
#include "avr_ioport.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_time.h"

/* The read side of simavr's UART input FIFO (declared in avr_uart.h). */
DEFINE_FIFO(uint16_t, uart_fifo);

#define LINE_MAX_BYTES 20000    /* `rx` with 4096 bytes in hex, and room to spare */
/* Host bytes not yet on the wire: six seconds at 115200 baud. The USB-serial chip would
 * make the host wait beyond its buffer; here the excess is dropped and counted. */
#define RX_QUEUE_BYTES 65536
#define TX_BATCH_BYTES 4096
/* A third byte arriving while two wait unread in UDR (and one in the shift register) is a
 * data overrun (DOR) on the ATmega2560: the chip loses it. simavr's own FIFO would keep it. */
#define RX_BYTES_BEFORE_OVERRUN 3
#define EXIT_AVR_STOPPED 3

typedef struct {
    char port;
    int bit;
} pin_t;

static struct {
    const char *mcu;
    uint32_t frequency;
    pin_t inlet, exhaust, trigger, echo;
    int adc_channel;
    uint32_t echo_delay_us;     /* HC-SR04: end of trigger to rising echo */
    uint32_t no_echo_us;        /* HC-SR04: echo width when nothing answers */
    uint32_t min_trigger_us;    /* shorter trigger pulses do not start a measurement */
    const char *loop_symbol;    /* called once per pass of the Arduino main loop */
} config = {
    .mcu = "atmega2560",
    .frequency = 16000000,
    .inlet = {'E', 3},
    .exhaust = {'H', 3},
    .trigger = {'H', 6},
    .echo = {'B', 4},
    .adc_channel = 0,
    .echo_delay_us = 450,
    .no_echo_us = 38000,
    .min_trigger_us = 10,
    .loop_symbol = "_Z14serialEventRunv",
};

static avr_t *avr;
static avr_uart_t *uart0;
static avr_irq_t *uart_input_irq;
static avr_irq_t *adc_input_irq;
static avr_irq_t *echo_irq;
static avr_irq_t *inlet_irq, *exhaust_irq, *trigger_irq;
static FILE *to_controller;
static avr_cycle_count_t cycle_base;     /* avr->cycle at the last reset */

static uint8_t inlet_level, exhaust_level;

static struct {
    avr_cycle_count_t trigger_rise;   /* 0: trigger low */
    int busy;                         /* from a valid trigger until the echo ends */
    uint32_t width_us;
} sensor;

static uint8_t rx_queue[RX_QUEUE_BYTES];
static size_t rx_head, rx_count;
static int rx_pumping;

static uint8_t tx_batch[TX_BATCH_BYTES];
static size_t tx_length;

static uint32_t loop_marker_pc;   /* 0: no marker found */
static uint16_t data_end;         /* first SRAM byte above .data and .bss */

/* Counters since the last reset; `window_` ones since the last `stats`. A pass of the main
 * loop is timed busy: the firmware idles asleep between passes until an interrupt, and the
 * cycles asleep (`asleep_in_pass`) are not time it kept anything waiting. */
static struct {
    uint64_t loops, window_loops;
    avr_cycle_count_t last_loop, loop_max, window_loop_max, asleep_in_pass, asleep;
    uint16_t min_sp, window_min_sp;
    uint64_t rx_bytes, rx_overruns, rx_dropped, rx_backlog_max, tx_bytes;
    uint64_t triggers, triggers_ignored, triggers_short, conversions;
} stats;

static char line[LINE_MAX_BYTES];

static avr_cycle_count_t now(void) { return avr->cycle - cycle_base; }

static void fail(const char *format, ...) {
    va_list args;
    va_start(args, format);
    fputs("pma_simavr: ", stderr);
    vfprintf(stderr, format, args);
    fputc('\n', stderr);
    va_end(args);
    exit(2);
}

static void flush_tx(void) {
    if (tx_length == 0) return;
    fputs("tx ", to_controller);
    for (size_t i = 0; i < tx_length; ++i) fprintf(to_controller, "%02x", tx_batch[i]);
    fputc('\n', to_controller);
    tx_length = 0;
}

/* Ask the controller and wait for its one-number answer. */
static uint32_t ask(const char *what) {
    flush_tx();
    fprintf(to_controller, "%s %llu\n", what, (unsigned long long)now());
    fflush(to_controller);
    if (!fgets(line, sizeof line, stdin)) exit(0);   /* controller gone */
    char *end;
    errno = 0;
    unsigned long value = strtoul(line, &end, 10);
    if (errno || end == line || (*end != '\n' && *end != '\0'))
        fail("bad answer to %s: %s", what, line);
    return (uint32_t)value;
}

/* ---- UART0: the USB-serial link. */

static void on_uart_output(avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    if (tx_length == TX_BATCH_BYTES) flush_tx();
    tx_batch[tx_length++] = (uint8_t)value;
    stats.tx_bytes++;
}

/* One host byte per frame time, as the USB-serial chip puts them on the wire. */
static avr_cycle_count_t rx_pump(avr_t *avr_, avr_cycle_count_t when, void *param) {
    (void)avr_;
    (void)param;
    if (rx_count == 0) {
        rx_pumping = 0;
        return 0;
    }
    uint8_t byte = rx_queue[rx_head];
    rx_head = (rx_head + 1) % RX_QUEUE_BYTES;
    rx_count--;
    stats.rx_bytes++;
    uint64_t backlog = uart_fifo_get_read_size(&uart0->input);
    if (backlog > stats.rx_backlog_max) stats.rx_backlog_max = backlog;
    if (backlog >= RX_BYTES_BEFORE_OVERRUN)
        stats.rx_overruns++;
    else
        avr_raise_irq(uart_input_irq, byte);
    return when + uart0->cycles_per_byte;
}

static int hex_value(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}

static void queue_rx(const char *hex) {
    for (; hex[0] && hex[0] != '\n'; hex += 2) {
        int high = hex_value(hex[0]), low = hex[1] ? hex_value(hex[1]) : -1;
        if (high < 0 || low < 0) fail("bad hex in rx");
        if (rx_count == RX_QUEUE_BYTES) {
            stats.rx_dropped++;
            continue;
        }
        rx_queue[(rx_head + rx_count++) % RX_QUEUE_BYTES] = (uint8_t)(high << 4 | low);
    }
    if (rx_count && !rx_pumping) {
        rx_pumping = 1;
        avr_cycle_timer_register(avr, uart0->cycles_per_byte, rx_pump, NULL);
    }
}

/* ---- Pressure sensor on the ADC. */

static void on_adc_trigger(avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    union {
        avr_adc_mux_t mux;
        uint32_t value;
    } event = {.value = value};
    if (event.mux.kind != ADC_MUX_SINGLE || (int)event.mux.src != config.adc_channel) return;
    stats.conversions++;
    avr_raise_irq(adc_input_irq, ask("adc"));
}

/* ---- HC-SR04: trigger in, echo out. */

static avr_cycle_count_t echo_fall(avr_t *avr_, avr_cycle_count_t when, void *param) {
    (void)avr_;
    (void)when;
    (void)param;
    avr_raise_irq(echo_irq, 0);
    sensor.busy = 0;
    return 0;
}

static avr_cycle_count_t echo_rise(avr_t *avr_, avr_cycle_count_t when, void *param) {
    (void)avr_;
    (void)when;
    (void)param;
    avr_raise_irq(echo_irq, 1);
    avr_cycle_timer_register_usec(avr, sensor.width_us, echo_fall, NULL);
    return 0;
}

static void on_trigger(avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    if (value) {
        sensor.trigger_rise = now() ? now() : 1;
        return;
    }
    if (!sensor.trigger_rise) return;
    avr_cycle_count_t high = now() - sensor.trigger_rise;
    sensor.trigger_rise = 0;
    stats.triggers++;
    if (sensor.busy) {
        stats.triggers_ignored++;   /* still measuring: the sensor ignores it */
        return;
    }
    if (high < (avr_cycle_count_t)avr_usec_to_cycles(avr, config.min_trigger_us)) {
        stats.triggers_short++;
        return;
    }
    uint32_t echo_us = ask("trig");
    sensor.busy = 1;
    sensor.width_us = echo_us ? echo_us : config.no_echo_us;
    avr_cycle_timer_register_usec(avr, config.echo_delay_us, echo_rise, NULL);
}

/* ---- Valves. */

static void report_valves(void) {
    flush_tx();
    fprintf(to_controller, "valves %llu %u %u\n", (unsigned long long)now(), inlet_level,
            exhaust_level);
}

static void on_valve(avr_irq_t *irq, uint32_t value, void *param) {
    (void)param;
    uint8_t level = value ? 1 : 0;
    if (irq == inlet_irq) inlet_level = level;
    else exhaust_level = level;
    report_valves();
}

/* ---- Set-up. */

static avr_irq_t *pin_irq(pin_t pin) {
    avr_irq_t *irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(pin.port), pin.bit);
    if (!irq) fail("no pin P%c%d on %s", pin.port, pin.bit, config.mcu);
    return irq;
}

static pin_t parse_pin(const char *text) {
    pin_t pin = {text[0], text[0] ? atoi(text + 1) : -1};
    if (pin.port < 'A' || pin.port > 'L' || pin.bit < 0 || pin.bit > 7 || strlen(text) != 2)
        fail("bad pin '%s' (port letter and bit, e.g. E3)", text);
    return pin;
}

static avr_uart_t *find_uart(char name) {
    for (avr_io_t *io = avr->io_port; io; io = io->next)
        if (!strcmp(io->kind, "uart") && ((avr_uart_t *)io)->name == name)
            return (avr_uart_t *)io;
    fail("no UART%c on %s", name, config.mcu);
    return NULL;
}

static void find_symbols(elf_firmware_t *firmware) {
    for (uint32_t i = 0; i < firmware->symbolcount; ++i) {
        const avr_symbol_t *symbol = firmware->symbol[i];
        if (!strcmp(symbol->symbol, config.loop_symbol)) loop_marker_pc = symbol->addr;
        /* Data addresses carry the linker's 0x800000 offset. */
        if (!strcmp(symbol->symbol, "_end")) data_end = symbol->addr & 0xffff;
    }
    if (!data_end) fail("no _end symbol in the firmware: cannot place the stack");
    if (!loop_marker_pc)
        fprintf(stderr, "pma_simavr: no %s in the firmware: loop times not measured\n",
                config.loop_symbol);
}

static void avr_log_to_stderr(avr_t *avr_, const int level, const char *format, va_list ap) {
    if (level > (avr_ ? avr_->log : LOG_WARNING)) return;
    vfprintf(stderr, format, ap);
}

static void reset_state(void) {
    cycle_base = avr->cycle;
    memset(&sensor, 0, sizeof sensor);
    memset(&stats, 0, sizeof stats);
    stats.min_sp = stats.window_min_sp = avr->ramend;
    rx_head = rx_count = 0;
    rx_pumping = 0;
    tx_length = 0;
    /* Power is off between an unplug and the reset: the valves closed, the echo low. */
    avr_raise_irq(echo_irq, 0);
    avr_raise_irq(inlet_irq, 0);
    avr_raise_irq(exhaust_irq, 0);
    avr_raise_irq(trigger_irq, 0);
    inlet_level = exhaust_level = 0;
    report_valves();
}

static void print_stats(void) {
    flush_tx();
    fprintf(to_controller,
            "stats cycle=%llu loops=%llu loop_max_cycles=%llu window_loops=%llu "
            "window_loop_max_cycles=%llu min_sp=%u window_min_sp=%u data_end=%u ramend=%u "
            "rx_bytes=%llu rx_overruns=%llu rx_dropped=%llu rx_backlog_max=%llu tx_bytes=%llu "
            "triggers=%llu triggers_ignored=%llu triggers_short=%llu conversions=%llu "
            "asleep_cycles=%llu cycles_per_byte=%llu frequency=%u\n",
            (unsigned long long)now(), (unsigned long long)stats.loops,
            (unsigned long long)stats.loop_max, (unsigned long long)stats.window_loops,
            (unsigned long long)stats.window_loop_max, stats.min_sp, stats.window_min_sp,
            data_end, avr->ramend, (unsigned long long)stats.rx_bytes,
            (unsigned long long)stats.rx_overruns, (unsigned long long)stats.rx_dropped,
            (unsigned long long)stats.rx_backlog_max,
            (unsigned long long)stats.tx_bytes, (unsigned long long)stats.triggers,
            (unsigned long long)stats.triggers_ignored, (unsigned long long)stats.triggers_short,
            (unsigned long long)stats.conversions, (unsigned long long)stats.asleep,
            (unsigned long long)uart0->cycles_per_byte,
            avr->frequency);
    stats.window_loops = 0;
    stats.window_loop_max = 0;
    stats.window_min_sp = avr->ramend;
}

/* Run to `target` (cycles since reset), watching the stack and the main loop's passes. */
static void run_to(avr_cycle_count_t target) {
    const uint16_t ram_start = avr->ioend + 1;
    while (now() < target) {
        const int sleeping = avr->state == cpu_Sleeping;
        const avr_cycle_count_t before = avr->cycle;
        int state = avr_run(avr);
        if (sleeping) {     /* simavr jumps a sleep ahead to the next timer or interrupt */
            stats.asleep_in_pass += avr->cycle - before;
            stats.asleep += avr->cycle - before;
        }
        if (state == cpu_Done || state == cpu_Crashed) {
            flush_tx();
            fprintf(to_controller, "error the AVR %s at cycle %llu, pc 0x%x\n",
                    state == cpu_Done ? "stopped (sleep with interrupts off)" : "crashed",
                    (unsigned long long)now(), avr->pc);
            fflush(to_controller);
            exit(EXIT_AVR_STOPPED);
        }
        uint16_t sp = avr->data[R_SPL] | (uint16_t)avr->data[R_SPH] << 8;
        if (sp < stats.window_min_sp && sp >= ram_start) {
            stats.window_min_sp = sp;
            if (sp < stats.min_sp) stats.min_sp = sp;
        }
        if (avr->pc == loop_marker_pc && loop_marker_pc) {
            avr_cycle_count_t at = now();
            if (stats.loops) {
                avr_cycle_count_t pass = at - stats.last_loop - stats.asleep_in_pass;
                if (pass > stats.loop_max) stats.loop_max = pass;
                if (pass > stats.window_loop_max) stats.window_loop_max = pass;
            }
            stats.last_loop = at;
            stats.asleep_in_pass = 0;
            stats.loops++;
            stats.window_loops++;
        }
    }
}

static void sleep_without_waiting(avr_t *avr_, avr_cycle_count_t how_long) {
    (void)avr_;
    (void)how_long;
}

static void usage(void) {
    fputs("usage: pma_simavr [--mcu NAME] [--frequency HZ] [--inlet PIN] [--exhaust PIN]\n"
          "       [--trigger PIN] [--echo PIN] [--adc-channel N] [--echo-delay-us US]\n"
          "       [--no-echo-us US] [--min-trigger-us US] [--loop-symbol NAME] FIRMWARE.elf\n"
          "PIN is a port letter and bit (E3). The controller talks on stdin/stdout.\n",
          stderr);
    exit(2);
}

int main(int argc, char **argv) {
    static const struct option options[] = {
        {"mcu", required_argument, NULL, 'm'},
        {"frequency", required_argument, NULL, 'f'},
        {"inlet", required_argument, NULL, 'i'},
        {"exhaust", required_argument, NULL, 'x'},
        {"trigger", required_argument, NULL, 't'},
        {"echo", required_argument, NULL, 'e'},
        {"adc-channel", required_argument, NULL, 'a'},
        {"echo-delay-us", required_argument, NULL, 'd'},
        {"no-echo-us", required_argument, NULL, 'n'},
        {"min-trigger-us", required_argument, NULL, 'w'},
        {"loop-symbol", required_argument, NULL, 'l'},
        {NULL, 0, NULL, 0},
    };
    for (int option; (option = getopt_long(argc, argv, "", options, NULL)) != -1;) {
        switch (option) {
            case 'm': config.mcu = optarg; break;
            case 'f': config.frequency = (uint32_t)strtoul(optarg, NULL, 10); break;
            case 'i': config.inlet = parse_pin(optarg); break;
            case 'x': config.exhaust = parse_pin(optarg); break;
            case 't': config.trigger = parse_pin(optarg); break;
            case 'e': config.echo = parse_pin(optarg); break;
            case 'a': config.adc_channel = atoi(optarg); break;
            case 'd': config.echo_delay_us = (uint32_t)strtoul(optarg, NULL, 10); break;
            case 'n': config.no_echo_us = (uint32_t)strtoul(optarg, NULL, 10); break;
            case 'w': config.min_trigger_us = (uint32_t)strtoul(optarg, NULL, 10); break;
            case 'l': config.loop_symbol = optarg; break;
            default: usage();
        }
    }
    if (optind != argc - 1) usage();

    /* The controller stops us by closing stdin; a signal to our group is its business. */
    signal(SIGINT, SIG_IGN);
    signal(SIGTERM, SIG_IGN);
    signal(SIGHUP, SIG_IGN);
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    /* stdout is the protocol; anything simavr prints goes to stderr instead. */
    int protocol_fd = dup(STDOUT_FILENO);
    if (protocol_fd < 0 || dup2(STDERR_FILENO, STDOUT_FILENO) < 0) fail("dup: %s", strerror(errno));
    to_controller = fdopen(protocol_fd, "w");
    setvbuf(to_controller, NULL, _IOFBF, 1 << 16);
    avr_global_logger_set(avr_log_to_stderr);

    /* Room past the struct in case the library counts more fields than this header. */
    elf_firmware_t *firmware = calloc(1, sizeof(elf_firmware_t) + 4096);
    if (!firmware) fail("out of memory");
    if (elf_read_firmware(argv[optind], firmware) != 0)
        fail("cannot read the firmware %s", argv[optind]);
    avr = avr_make_mcu_by_name(config.mcu);
    if (!avr) fail("simavr has no MCU '%s'", config.mcu);
    avr_init(avr);
    /* simavr's raw mode paces a sleeping AVR to the wall clock (usleep); the controller keeps
     * time here, so a sleep just jumps the cycle count to the next timer or interrupt. */
    avr->sleep = sleep_without_waiting;
    avr->log = LOG_ERROR;
    firmware->frequency = config.frequency;
    avr_load_firmware(avr, firmware);
    avr->frequency = config.frequency;
    avr->vcc = avr->avcc = avr->aref = 5000;   /* the sensor is ratiometric to the same 5 V */
    find_symbols(firmware);

    uart0 = find_uart('0');
    uint32_t uart_flags = 0;   /* no console echo, no sleeping in polls */
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &uart_flags);
    uart_input_irq = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            on_uart_output, NULL);
    adc_input_irq = avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + config.adc_channel);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_OUT_TRIGGER),
                            on_adc_trigger, NULL);
    inlet_irq = pin_irq(config.inlet);
    exhaust_irq = pin_irq(config.exhaust);
    trigger_irq = pin_irq(config.trigger);
    echo_irq = pin_irq(config.echo);
    avr_irq_register_notify(inlet_irq, on_valve, NULL);
    avr_irq_register_notify(exhaust_irq, on_valve, NULL);
    avr_irq_register_notify(trigger_irq, on_trigger, NULL);
    reset_state();

    while (fgets(line, sizeof line, stdin)) {
        if (!strncmp(line, "run ", 4)) {
            run_to(strtoull(line + 4, NULL, 10));
        } else if (!strncmp(line, "rx ", 3)) {
            queue_rx(line + 3);
            continue;   /* no answer */
        } else if (!strcmp(line, "reset\n")) {
            avr_reset(avr);
            reset_state();
        } else if (!strcmp(line, "stats\n")) {
            print_stats();
            fflush(to_controller);
            continue;
        } else {
            fail("unknown command: %s", line);
        }
        flush_tx();
        fprintf(to_controller, "done %llu\n", (unsigned long long)now());
        fflush(to_controller);
    }
    return 0;
}

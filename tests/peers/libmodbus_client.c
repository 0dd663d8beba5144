/*
 * A libmodbus client for the interop tests: one connection, a list of operations, one output line each.
 *
 *   libmodbus_client tcp HOST PORT UNIT OP...
 *   libmodbus_client rtu DEVICE BAUD PARITY(N|E|O) STOP UNIT OP...
 *
 * OP is one argument, fields separated by ':' (values decimal or 0x hex):
 *   rh:ADDR:N      FC 03, prints the N registers in decimal
 *   ri:ADDR:N      FC 04
 *   wr:ADDR:V      FC 06, prints "ok"
 *   wh:ADDR:V,V... FC 16, prints "ok"
 *   rc:ADDR:N      FC 01, prints the N coils as 0/1
 *   wc:ADDR:B      FC 05
 *   wm:ADDR:B,B... FC 15
 * A Modbus exception prints "exception N" (libmodbus maps them to errno MODBUS_ENOBASE + N) and the run goes
 * on; any other error prints "error: ..." and exits 1. Build:
 *   gcc libmodbus_client.c -o libmodbus_client $(pkg-config --cflags --libs libmodbus)
 */
#include <errno.h>
#include <modbus.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAX_VALUES 125

static long num(const char *s) { return strtol(s, NULL, 0); }

/* Parse "V,V,..." into out; returns the count. */
static int list(const char *s, uint16_t *out) {
    int n = 0;
    char *copy = strdup(s), *save = NULL;
    for (char *t = strtok_r(copy, ",", &save); t && n < MAX_VALUES; t = strtok_r(NULL, ",", &save))
        out[n++] = (uint16_t)num(t);
    free(copy);
    return n;
}

/* Report a failed call: exceptions are answers, anything else ends the run. */
static int failed(const char *op) {
    if (errno > MODBUS_ENOBASE && errno <= MODBUS_ENOBASE + 0xFF && errno < EMBBADCRC) {
        printf("exception %d\n", errno - MODBUS_ENOBASE);
        return 0;
    }
    printf("error: %s: %s\n", op, modbus_strerror(errno));
    return 1;
}

static int run_op(modbus_t *ctx, const char *op) {
    char kind[8] = {0};
    const char *p = strchr(op, ':');
    if (!p || p - op >= (long)sizeof kind) {
        printf("error: bad op %s\n", op);
        return 1;
    }
    memcpy(kind, op, p - op);
    int addr = (int)num(p + 1);
    const char *rest = strchr(p + 1, ':');
    if (!rest) {
        printf("error: bad op %s\n", op);
        return 1;
    }
    rest++;
    uint16_t regs[MAX_VALUES];
    uint8_t bits[MAX_VALUES];
    int n, rc;
    if (!strcmp(kind, "rh") || !strcmp(kind, "ri")) {
        n = (int)num(rest);
        if (n < 1 || n > MAX_VALUES) return printf("error: bad count\n"), 1;
        rc = kind[1] == 'h' ? modbus_read_registers(ctx, addr, n, regs)
                            : modbus_read_input_registers(ctx, addr, n, regs);
        if (rc < 0) return failed(op);
        for (int i = 0; i < rc; i++) printf(i ? " %u" : "%u", regs[i]);
        printf("\n");
    } else if (!strcmp(kind, "rc")) {
        n = (int)num(rest);
        if (n < 1 || n > MAX_VALUES) return printf("error: bad count\n"), 1;
        rc = modbus_read_bits(ctx, addr, n, bits);
        if (rc < 0) return failed(op);
        for (int i = 0; i < rc; i++) printf(i ? " %u" : "%u", bits[i]);
        printf("\n");
    } else if (!strcmp(kind, "wr")) {
        if (modbus_write_register(ctx, addr, (uint16_t)num(rest)) < 0) return failed(op);
        printf("ok\n");
    } else if (!strcmp(kind, "wh")) {
        n = list(rest, regs);
        if (modbus_write_registers(ctx, addr, n, regs) < 0) return failed(op);
        printf("ok\n");
    } else if (!strcmp(kind, "wc")) {
        if (modbus_write_bit(ctx, addr, num(rest) ? 1 : 0) < 0) return failed(op);
        printf("ok\n");
    } else if (!strcmp(kind, "wm")) {
        n = list(rest, regs);
        for (int i = 0; i < n; i++) bits[i] = regs[i] ? 1 : 0;
        if (modbus_write_bits(ctx, addr, n, bits) < 0) return failed(op);
        printf("ok\n");
    } else {
        printf("error: unknown op %s\n", op);
        return 1;
    }
    return 0;
}

int main(int argc, char **argv) {
    modbus_t *ctx = NULL;
    int first;
    if (argc >= 5 && !strcmp(argv[1], "tcp")) {
        ctx = modbus_new_tcp(argv[2], (int)num(argv[3]));
        if (ctx) modbus_set_slave(ctx, (int)num(argv[4]));
        first = 5;
    } else if (argc >= 7 && !strcmp(argv[1], "rtu")) {
        ctx = modbus_new_rtu(argv[2], (int)num(argv[3]), argv[4][0], 8, (int)num(argv[5]));
        if (ctx) modbus_set_slave(ctx, (int)num(argv[6]));
        first = 7;
    } else {
        fprintf(stderr, "usage: %s tcp HOST PORT UNIT OP... | rtu DEV BAUD PARITY STOP UNIT OP...\n", argv[0]);
        return 2;
    }
    if (!ctx) {
        printf("error: cannot create context: %s\n", modbus_strerror(errno));
        return 1;
    }
    modbus_set_response_timeout(ctx, 2, 0);
    if (modbus_connect(ctx) < 0) {
        printf("error: connect: %s\n", modbus_strerror(errno));
        modbus_free(ctx);
        return 1;
    }
    int status = 0;
    for (int i = first; i < argc && !status; i++) status = run_op(ctx, argv[i]);
    fflush(stdout);
    modbus_close(ctx);
    modbus_free(ctx);
    return status;
}

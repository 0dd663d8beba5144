/*
 * SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator.
 *
 * Built on libmodbus 3.1.6 (RTU backend: serial port setup, response
 * framing/CRC, modbus_reply() for FC 03/04/06/16/23, modbus_reply_exception(),
 * modbus_send_raw_request() for the raw FC 08 / FC 43 replies).
 * The receive side is our own t3.5 framer on the libmodbus serial fd because
 * modbus_receive() cannot frame FC 08 and FC 43 requests (see DECISIONS.md).
 *
 * Build: gcc -O2 -Wall -Wextra -o sim sim.c $(pkg-config --cflags --libs libmodbus)
 * Usage: ./sim --serial DEVICE [--baud 19200] [--parity none|even|odd]
 *              [--state FILE] [--slave 1]
 */
#define _POSIX_C_SOURCE 200809L
#include <errno.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <time.h>
#include <unistd.h>

#include <modbus.h>

/* ------------------------------------------------------------------ */
/* Register map (chapter 4)                                            */
/* ------------------------------------------------------------------ */
#define TX_START 2000 /* TxPDO, actual values, read only   */
#define TX_COUNT 24   /* 2000..2023                          */
#define RX_START 3000 /* RxPDO, setpoints, read/write        */
#define RX_COUNT 4    /* 3000..3003                          */
#define MAP_START TX_START
#define MAP_COUNT (RX_START + RX_COUNT - TX_START) /* 1004 */
#define MAX_REGS_PER_REQ 48                        /* manual: n = 1..48 */

#define R_STATUS 2000
#define R_ACT_SPEED 2001
#define R_TX_TORQUE 2002
#define R_CURRENT 2003
#define R_POWER 2004
#define R_ERROR 2005
#define R_TEMP_PS 2006
#define R_TEMP_MOT 2007
#define R_OUT_VOLT 2008
#define R_DC_VOLT 2009
#define R_HW_ID 2010
#define R_HW_VER 2012
#define R_SW_ID 2014
#define R_SW_VER 2016
#define R_MAX_IQ 2018
#define R_MAX_SPEED 2019
#define R_SPEED_SCALE 2020
#define R_CURR_SCALE 2022
#define R_CONTROL 3000
#define R_TARGET_SPEED 3001
#define R_TORQUE_LIMIT 3002
#define R_WATCHDOG 3003

/* fixed device data (our product choice, see DECISIONS.md) */
#define HW_ID 0x00005D20u
#define HW_VERSION 0x00020010u /* 2.16, the manual's example */
#define SW_ID 0x00000322u
#define SW_VERSION 0x00040012u /* 4.18 */
#define MAX_IQ 200             /* 20.0 A */
#define MAX_SPEED_RAW 0x3FFF   /* 0x3FFF = speed scaling -> 1000.0 Hz */
#define SPEED_SCALING 60000000 /* 60000.000 rpm = 1000 Hz (1 pole pair) */
#define CURRENT_SCALING 20000  /* 20.000 A */
#define MAX_SPEED_01HZ 10000   /* 1000.0 Hz in 0.1 Hz */
#define DC_VOLTAGE 5600        /* 560.0 V */
#define TEMP_PS 170            /* 17.0 degC, the manual's example value */
#define TEMP_MOTOR 235         /* 23.5 degC */
#define ERR_WATCHDOG 0x8130    /* DS402/CiA301 "life guard / heartbeat error" */

static uint16_t regs[MAP_COUNT];
#define REG(a) regs[(a) - MAP_START]

/* FC 03 and FC 04 are treated identically (manual 3.1): both libmodbus tables
 * point to the same storage. */
static modbus_mapping_t mapping = {
    .nb_input_registers = MAP_COUNT,
    .start_input_registers = MAP_START,
    .nb_registers = MAP_COUNT,
    .start_registers = MAP_START,
    .tab_input_registers = regs,
    .tab_registers = regs,
};

/* ------------------------------------------------------------------ */
/* Object dictionary (chapter 5), FC 43 / MEI 0x0D                     */
/* ------------------------------------------------------------------ */
enum otype { U16, I16, U32, I32 };
struct object {
    uint16_t index;
    enum otype type;
    int writable;
    int reg; /* register holding the value (32 bit: high word first) */
    const char *name;
};
static const struct object objects[] = {
    {2, U32, 0, R_HW_ID, "Hardware ID"},
    {5, U32, 0, R_HW_VER, "Hardware Version"},
    {16, U32, 0, R_SW_ID, "Software ID"},
    {17, U32, 0, R_SW_VER, "Software Version"},
    {33, I16, 0, R_DC_VOLT, "DC Voltage"},
    {41, I16, 0, R_TEMP_PS, "Temperature Power Stage"},
    {63, I16, 0, R_TEMP_MOT, "Temperature Motor"},
    {67, U16, 0, R_STATUS, "Status Word"},
    {68, U16, 1, R_CONTROL, "Control Word"},
    {70, U16, 0, R_ERROR, "Error Code"},
    {120, I16, 0, R_MAX_SPEED, "Max Speed"},
    {168, I16, 0, R_ACT_SPEED, "Actual Speed"},
    {171, I16, 0, R_MAX_IQ, "Max Iq Current"},
    {177, I32, 0, R_SPEED_SCALE, "Speed Scaling"},
    {182, I32, 0, R_CURR_SCALE, "Current Scaling"},
    {209, I16, 1, R_TORQUE_LIMIT, "Target Torque Limit"},
    {210, I16, 1, R_TARGET_SPEED, "Target Velocity"},
    {390, I16, 0, R_POWER, "Actual Output Power"},
    {431, I16, 0, R_CURRENT, "Actual Apparent Current"},
    {434, I16, 0, R_OUT_VOLT, "Output Voltage"},
};
#define N_OBJECTS (sizeof(objects) / sizeof(objects[0]))

#define SDO_NOT_EXIST 0xFFFF000Bu
#define SDO_READ_ONLY 0xFFFF000Au
#define SDO_TOO_LONG 0xFFFF0012u
#define SDO_TOO_SHORT 0xFFFF0013u
#define SDO_NO_SUBINDEX 0xFFFF0014u

/* ------------------------------------------------------------------ */
/* Drive model: DS402 state machine, velocity ramp, watchdog           */
/* ------------------------------------------------------------------ */
enum dstate { S_SOD, S_RTSO, S_SO, S_OE, S_QSA, S_FAULT };
static const char *state_names[] = {"switch_on_disabled", "ready_to_switch_on",
                                    "switched_on",        "operation_enabled",
                                    "quick_stop_active",  "fault"};
static enum dstate dstate = S_SOD;
static double act_speed;    /* 0.1 Hz */
static uint16_t error_code; /* object 70 */
static uint16_t prev_cw;    /* for the fault-reset edge */
static double wd_deadline;  /* monotonic seconds; armed when 3003 written */
static double last_tick;
static int ramping;         /* torque-limited acceleration in progress */
static int limit_active;

#define COAST_RATE 2000.0      /* 0.1 Hz/s: power stage off (200 Hz/s) */
#define QUICKSTOP_RATE 10000.0 /* 0.1 Hz/s: quick stop ramp (1000 Hz/s) */
#define FULL_CURRENT_RATE 10000.0 /* 0.1 Hz/s at Max Iq (1000 Hz/s) */

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec / 1e9;
}

static void put32(int reg, uint32_t v)
{
    REG(reg) = (uint16_t)(v >> 16);
    REG(reg + 1) = (uint16_t)(v & 0xFFFF);
}

static void enter_fault(uint16_t code)
{
    if (dstate != S_FAULT) {
        dstate = S_FAULT;
        error_code = code;
    }
}

/* Evaluate the control word (DS402 device control, level triggered except
 * the fault reset, which is the rising edge of bit 7). */
static void eval_control_word(double now)
{
    uint16_t cw = REG(R_CONTROL);
    int fault_reset = (cw & 0x80) && !(prev_cw & 0x80);
    prev_cw = cw;

    if (dstate == S_FAULT) {
        if (fault_reset) {
            dstate = S_SOD;
            error_code = 0;
            wd_deadline = now + REG(R_WATCHDOG) / 1000.0;
        }
        return;
    }
    if (cw & 0x80)
        return; /* bit 7 set: no other command is interpreted */

    int disable_voltage = (cw & 0x02) == 0;
    int quick_stop = (cw & 0x06) == 0x02;
    int shutdown = (cw & 0x07) == 0x06;
    int switch_on = (cw & 0x0F) == 0x07;
    int enable_op = (cw & 0x0F) == 0x0F;

    switch (dstate) {
    case S_SOD:
        if (shutdown)
            dstate = S_RTSO;
        break;
    case S_RTSO:
        if (disable_voltage || quick_stop)
            dstate = S_SOD;
        else if (switch_on)
            dstate = S_SO;
        else if (enable_op)
            dstate = S_OE; /* transitions 3 + 4 */
        break;
    case S_SO:
        if (disable_voltage || quick_stop)
            dstate = S_SOD;
        else if (shutdown)
            dstate = S_RTSO;
        else if (enable_op)
            dstate = S_OE;
        break;
    case S_OE:
        if (disable_voltage)
            dstate = S_SOD;
        else if (quick_stop)
            dstate = S_QSA;
        else if (shutdown)
            dstate = S_RTSO;
        else if (switch_on)
            dstate = S_SO;
        break;
    case S_QSA:
        if (disable_voltage)
            dstate = S_SOD;
        break;
    default:
        break;
    }
}

static double dabs(double v) { return v < 0 ? -v : v; }

static int16_t clamp16(double v)
{
    if (v > 32767)
        return 32767;
    if (v < -32768)
        return -32768;
    return (int16_t)(v < 0 ? v - 0.5 : v + 0.5);
}

/* Advance the simulation to 'now' and refresh the TxPDO image. */
static void update_model(double now)
{
    double dt = now - last_tick;
    if (dt < 0)
        dt = 0;
    if (dt > 1.0)
        dt = 1.0;
    last_tick = now;

    /* watchdog (object "Watchdog", register 3003): active whenever != 0 */
    if (REG(R_WATCHDOG) != 0 && dstate != S_FAULT && now > wd_deadline)
        enter_fault(ERR_WATCHDOG);

    eval_control_word(now);

    int16_t tgt_raw = (int16_t)REG(R_TARGET_SPEED);
    int16_t tl_raw = (int16_t)REG(R_TORQUE_LIMIT);
    int eff_i = abs((int)tl_raw);
    if (eff_i > MAX_IQ)
        eff_i = MAX_IQ; /* limited by the drive peak current */

    double target = 0;
    double rate;
    limit_active = 0;
    if (dstate == S_OE && !(REG(R_CONTROL) & 0x100)) {
        target = tgt_raw;
        if (target > MAX_SPEED_01HZ) {
            target = MAX_SPEED_01HZ;
            limit_active = 1;
        } else if (target < -MAX_SPEED_01HZ) {
            target = -MAX_SPEED_01HZ;
            limit_active = 1;
        }
    }
    if (dstate == S_OE) {
        double acc = FULL_CURRENT_RATE * eff_i / MAX_IQ;
        int accelerating = (target * act_speed >= 0) && dabs(target) > dabs(act_speed);
        rate = accelerating ? acc : (acc > COAST_RATE ? acc : COAST_RATE);
        if (accelerating && eff_i == 0 && target != act_speed)
            limit_active = 1;
    } else if (dstate == S_QSA) {
        rate = QUICKSTOP_RATE;
    } else {
        rate = COAST_RATE;
    }
    double diff = target - act_speed;
    double step = rate * dt;
    ramping = 0;
    if (dabs(diff) <= step) {
        act_speed = target;
    } else {
        act_speed += diff > 0 ? step : -step;
        ramping = 1;
    }
    if (dstate == S_QSA && act_speed == 0)
        dstate = S_SOD; /* quick stop option: ramp, then switch on disabled */

    /* status word */
    static const uint16_t base[] = {0x0040, 0x0021, 0x0023, 0x0027, 0x0007, 0x0008};
    uint16_t sw = base[dstate] | 0x0010 /* voltage enabled: DC link charged */
                  | 0x0200 /* remote: control channel Modbus */;
    if (dstate == S_OE && act_speed == target)
        sw |= 0x0400; /* target reached */
    if (limit_active)
        sw |= 0x0800; /* internal limit active */
    REG(R_STATUS) = sw;

    REG(R_ACT_SPEED) = (uint16_t)clamp16(act_speed);
    REG(R_TX_TORQUE) = REG(R_TORQUE_LIMIT);
    double volt = 0, cur = 0;
    if (dstate == S_OE || dstate == S_QSA) {
        volt = dabs(act_speed) * 0.4; /* V/f: 400.0 V at 1000 Hz, 0.1 V */
        if (ramping && dstate == S_OE && eff_i > 0)
            cur = eff_i;
        else if (ramping && dstate == S_QSA)
            cur = MAX_IQ;
        else
            cur = 10 + dabs(act_speed) / 500.0; /* magnetising + load */
    }
    double power = 1.7320508 * (volt / 10.0) * (cur / 10.0) * 0.8 / 100.0;
    REG(R_OUT_VOLT) = (uint16_t)clamp16(volt);
    REG(R_CURRENT) = (uint16_t)clamp16(cur);
    REG(R_POWER) = (uint16_t)clamp16(power);
    REG(R_ERROR) = error_code;
    REG(R_TEMP_PS) = TEMP_PS;
    REG(R_TEMP_MOT) = TEMP_MOTOR;
    REG(R_DC_VOLT) = DC_VOLTAGE;
    put32(R_HW_ID, HW_ID);
    put32(R_HW_VER, HW_VERSION);
    put32(R_SW_ID, SW_ID);
    put32(R_SW_VER, SW_VERSION);
    REG(R_MAX_IQ) = MAX_IQ;
    REG(R_MAX_SPEED) = MAX_SPEED_RAW;
    put32(R_SPEED_SCALE, (uint32_t)SPEED_SCALING);
    put32(R_CURR_SCALE, (uint32_t)CURRENT_SCALING);
}

/* Called after the RxPDO registers [addr, addr+n) were written. */
static void after_rx_write(int addr, int n)
{
    double now = now_s();
    if (addr <= R_WATCHDOG && addr + n > R_WATCHDOG)
        wd_deadline = now + REG(R_WATCHDOG) / 1000.0; /* rewritten: re-arm */
    update_model(now);
}

/* ------------------------------------------------------------------ */
/* Serial line, counters                                               */
/* ------------------------------------------------------------------ */
static modbus_t *ctx;
static int slave_addr = 1;
static int baud = 19200;
static char parity_ch = 'N';
static const char *device;
static const char *state_file;

static struct {
    uint16_t bus_msg, bus_comm_err, bus_exc, slave_msg, slave_no_rsp;
} cnt;

static volatile sig_atomic_t stop_flag, dump_flag;
static void on_signal(int sig)
{
    if (sig == SIGUSR1)
        dump_flag = 1;
    else
        stop_flag = 1;
}

/* CRC as printed in the manual, chapter 6.3 */
static uint16_t ModbusCRC(uint8_t input, uint16_t last)
{
    uint16_t crc = last ^ (uint16_t)input;
    for (int i = 0; i < 8; i++)
        crc = (crc & 1) ? (uint16_t)((crc >> 1) ^ 0xA001) : (uint16_t)(crc >> 1);
    return crc;
}
static int crc_ok(const uint8_t *f, int n)
{
    if (n < 4)
        return 0;
    uint16_t crc = 0xFFFF;
    for (int i = 0; i < n - 2; i++)
        crc = ModbusCRC(f[i], crc);
    return f[n - 2] == (crc & 0xFF) && f[n - 1] == (crc >> 8);
}

/* ------------------------------------------------------------------ */
/* Request handling                                                    */
/* ------------------------------------------------------------------ */
static int is_bcast;

static void reply_exc(const uint8_t *req, int code)
{
    if (is_bcast) {
        cnt.slave_no_rsp++;
        return;
    }
    cnt.bus_exc++;
    modbus_reply_exception(ctx, req, (unsigned)code);
}

static void reply_raw(const uint8_t *raw, int len)
{
    if (is_bcast) {
        cnt.slave_no_rsp++;
        return;
    }
    modbus_send_raw_request(ctx, raw, len); /* libmodbus appends the CRC */
}

static void reply_lib(const uint8_t *req, int n)
{
    if (is_bcast)
        cnt.slave_no_rsp++;
    modbus_reply(ctx, req, n, &mapping); /* suppresses RTU broadcast replies */
}

static int in_tx(int a, int n) { return a >= TX_START && a + n <= TX_START + TX_COUNT; }
static int in_rx(int a, int n) { return a >= RX_START && a + n <= RX_START + RX_COUNT; }
static int rd16(const uint8_t *p) { return (p[0] << 8) | p[1]; }

static void handle_fc43(const uint8_t *f, int n)
{
    const uint8_t *p = f + 1; /* PDU */
    int pl = n - 3;
    if (pl < 2) {
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
        return;
    }
    if (p[1] != 0x0D) { /* only MEI type 0x0D (CANopen) is supported */
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_FUNCTION);
        return;
    }
    /* Two layouts: the table of 3.6 (with reserved byte) and the example of
     * 6.2 (without). Pick the one whose byte count matches the frame. */
    int hdr = 0; /* PDU bytes before data: 12 table, 11 example */
    for (int h = 12; h >= 11 && !hdr; h--) {
        if (pl < h)
            continue;
        int c = rd16(p + h - 2);
        int write = p[2] & 0x80;
        if (pl - h == (write ? c : 0))
            hdr = h;
    }
    if (!hdr) {
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
        return;
    }
    int s = (hdr == 12) ? 1 : 0; /* shift caused by the reserved byte */
    int ctrl = p[2];
    int node = p[3 + s];
    int index = rd16(p + 4 + s);
    int sub = p[6 + s];
    int count = rd16(p + 9 + s);
    const uint8_t *data = p + hdr;
    int write = ctrl & 0x80;

    if (count > 4) {
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
        return;
    }
    if (node != slave_addr) {
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS);
        return;
    }

    const struct object *o = NULL;
    for (size_t i = 0; i < N_OBJECTS; i++)
        if (objects[i].index == index)
            o = &objects[i];
    uint32_t sdo = 0;
    int size = 0;
    if (!o)
        sdo = SDO_NOT_EXIST;
    else if (sub != 0)
        sdo = SDO_NO_SUBINDEX;
    else {
        size = (o->type == U32 || o->type == I32) ? 4 : 2;
        if (write && !o->writable)
            sdo = SDO_READ_ONLY;
        else if ((write || count != 0) && count != size)
            sdo = count > size ? SDO_TOO_LONG : SDO_TOO_SHORT;
    }
    if (sdo) {
        if (is_bcast) {
            cnt.slave_no_rsp++;
            return;
        }
        uint8_t r[11] = {f[0], 0xAB, 0xFF, 0x00, 0x06, 0x0D, 0xCE,
                         (uint8_t)sdo, (uint8_t)(sdo >> 8), (uint8_t)(sdo >> 16),
                         (uint8_t)(sdo >> 24)};
        cnt.bus_exc++;
        modbus_send_raw_request(ctx, r, 11);
        return;
    }

    if (write) {
        uint32_t v = data[0] | (data[1] << 8);
        if (size == 4)
            v |= ((uint32_t)data[2] << 16) | ((uint32_t)data[3] << 24);
        if (size == 4)
            put32(o->reg, v);
        else
            REG(o->reg) = (uint16_t)v;
        after_rx_write(o->reg, size / 2);
        reply_raw(f, n - 2); /* echo of the request */
        return;
    }
    update_model(now_s());
    uint32_t v = (size == 4) ? ((uint32_t)REG(o->reg) << 16) | REG(o->reg + 1) : REG(o->reg);
    uint8_t r[24];
    memcpy(r, f, 1 + hdr);       /* address + PDU header */
    r[1 + 9 + s] = 0;            /* byte count = object size */
    r[1 + 10 + s] = (uint8_t)size;
    for (int i = 0; i < size; i++)
        r[1 + hdr + i] = (uint8_t)(v >> (8 * i)); /* little endian */
    reply_raw(r, 1 + hdr + size);
}

static void handle_fc08(const uint8_t *f, int n)
{
    int pl = n - 3;
    if (pl < 3) {
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
        return;
    }
    int sub = rd16(f + 2);
    if (sub == 0x00) { /* return query data: echo everything */
        reply_raw(f, n - 2);
        return;
    }
    if (sub < 0x0A || sub > 0x0F) {
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_FUNCTION);
        return;
    }
    if (pl != 5) {
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
        return;
    }
    uint16_t v = 0;
    switch (sub) {
    case 0x0A:
        memset(&cnt, 0, sizeof cnt);
        reply_raw(f, n - 2);
        return;
    case 0x0B: v = cnt.bus_msg; break;
    case 0x0C: v = cnt.bus_comm_err; break;
    case 0x0D: v = cnt.bus_exc; break;
    case 0x0E: v = cnt.slave_msg; break;
    case 0x0F: v = cnt.slave_no_rsp; break;
    }
    uint8_t r[6] = {f[0], 0x08, f[2], f[3], (uint8_t)(v >> 8), (uint8_t)v};
    reply_raw(r, 6);
}

static void process_frame(const uint8_t *f, int n)
{
    cnt.bus_msg++;
    int addr = f[0];
    if (addr != slave_addr && addr != 0)
        return;
    is_bcast = (addr == 0);
    cnt.slave_msg++;

    int fc = f[1];
    int pl = n - 3; /* PDU length incl. function code */
    update_model(now_s());

    switch (fc) {
    case 0x03:
    case 0x04: {
        if (pl != 5) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
            return;
        }
        int a = rd16(f + 2), q = rd16(f + 4);
        if (q < 1 || q > MAX_REGS_PER_REQ) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
            return;
        }
        if (!in_tx(a, q) && !in_rx(a, q)) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS);
            return;
        }
        reply_lib(f, n);
        return;
    }
    case 0x06: {
        if (pl != 5) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
            return;
        }
        int a = rd16(f + 2);
        if (!in_rx(a, 1)) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS);
            return;
        }
        reply_lib(f, n);
        after_rx_write(a, 1);
        return;
    }
    case 0x10: {
        if (pl < 6) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
            return;
        }
        int a = rd16(f + 2), q = rd16(f + 4), bc = f[6];
        if (q < 1 || q > MAX_REGS_PER_REQ || bc != 2 * q || pl != 6 + bc) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
            return;
        }
        if (!in_rx(a, q)) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS);
            return;
        }
        reply_lib(f, n);
        after_rx_write(a, q);
        return;
    }
    case 0x17: {
        if (pl < 10) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
            return;
        }
        int ra = rd16(f + 2), rq = rd16(f + 4);
        int wa = rd16(f + 6), wq = rd16(f + 8), bc = f[10];
        if (rq < 1 || rq > MAX_REGS_PER_REQ || wq < 1 || wq > MAX_REGS_PER_REQ ||
            bc != 2 * wq || pl != 10 + bc) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
            return;
        }
        if ((!in_tx(ra, rq) && !in_rx(ra, rq)) || !in_rx(wa, wq)) {
            reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS);
            return;
        }
        /* write first and let the drive react, then libmodbus writes the
         * same values again and reads (write-before-read, spec 6.17) */
        for (int i = 0; i < wq; i++)
            REG(wa + i) = (uint16_t)rd16(f + 11 + 2 * i);
        after_rx_write(wa, wq);
        reply_lib(f, n);
        return;
    }
    case 0x08:
        handle_fc08(f, n);
        return;
    case 0x2B:
        handle_fc43(f, n);
        return;
    default:
        if (fc & 0x80) { /* not a request (1..127): ignore, as on a shared bus */
            cnt.slave_no_rsp++;
            return;
        }
        reply_exc(f, MODBUS_EXCEPTION_ILLEGAL_FUNCTION);
        return;
    }
}

/* Expected request length (ADU incl. CRC) from what has arrived so far.
 * Returns candidates in c[] (0, 1 or 2). Frames of unknown shape are ended
 * by the t3.5 silence instead. */
static int expected_len(const uint8_t *b, int len, int c[2])
{
    if (len < 2)
        return 0;
    switch (b[1]) {
    case 0x01: case 0x02: case 0x03: case 0x04: case 0x05: case 0x06:
    case 0x08:
        c[0] = 8;
        return 1;
    case 0x07: case 0x0B: case 0x0C: case 0x11:
        c[0] = 4;
        return 1;
    case 0x0F: case 0x10:
        if (len < 7)
            return 0;
        c[0] = 9 + b[6];
        return 1;
    case 0x16:
        c[0] = 10;
        return 1;
    case 0x17:
        if (len < 11)
            return 0;
        c[0] = 13 + b[10];
        return 1;
    case 0x2B: {
        int k = 0;
        if (len < 3 || b[2] != 0x0D)
            return 0;
        int write = len >= 4 && (b[3] & 0x80);
        if (len >= 12) /* example layout, byte count at 10..11 */
            c[k++] = 14 + (write ? rd16(b + 10) : 0);
        if (len >= 13) /* table layout, byte count at 11..12 */
            c[k++] = 15 + (write ? rd16(b + 11) : 0);
        return k;
    }
    default:
        return 0;
    }
}

#define RXBUF 512
static uint8_t rxb[RXBUF];
static int rxlen;
static int rx_overflow;

/* Try to complete frames by predicted length. */
static void try_complete(void)
{
    for (;;) {
        int c[2];
        int k = expected_len(rxb, rxlen, c), done = 0;
        for (int i = 0; i < k && !done; i++) {
            if (c[i] <= rxlen && c[i] <= MODBUS_RTU_MAX_ADU_LENGTH && crc_ok(rxb, c[i])) {
                uint8_t fr[MODBUS_RTU_MAX_ADU_LENGTH];
                int fl = c[i];
                memcpy(fr, rxb, fl);
                memmove(rxb, rxb + fl, rxlen - fl);
                rxlen -= fl;
                process_frame(fr, fl);
                done = 1;
            }
        }
        if (!done)
            return;
    }
}

/* t3.5 of silence: whatever is buffered is one frame. */
static void end_of_frame(void)
{
    if (rxlen == 0 && !rx_overflow)
        return;
    if (!rx_overflow && rxlen >= 4 && rxlen <= MODBUS_RTU_MAX_ADU_LENGTH && crc_ok(rxb, rxlen)) {
        uint8_t fr[MODBUS_RTU_MAX_ADU_LENGTH];
        int fl = rxlen;
        memcpy(fr, rxb, fl);
        rxlen = 0;
        process_frame(fr, fl);
        return;
    }
    cnt.bus_msg++;
    cnt.bus_comm_err++;
    rxlen = 0;
    rx_overflow = 0;
}

/* ------------------------------------------------------------------ */
/* State dump                                                          */
/* ------------------------------------------------------------------ */
static void dump_state(void)
{
    if (!state_file)
        return;
    update_model(now_s());
    char tmp[4096];
    snprintf(tmp, sizeof tmp, "%s.tmp", state_file);
    FILE *fp = fopen(tmp, "w");
    if (!fp)
        return;
    fprintf(fp, "{\n  \"device\": \"SIEB & MEYER SD2x\",\n");
    fprintf(fp, "  \"config\": {\"slave_address\": %d, \"baud\": %d, \"parity\": \"%s\", "
                "\"stop_bits\": 1},\n",
            slave_addr, baud, parity_ch == 'N' ? "none" : parity_ch == 'E' ? "even" : "odd");
    fprintf(fp, "  \"drive_state\": \"%s\",\n", state_names[dstate]);
    fprintf(fp, "  \"registers\": {");
    int first = 1;
    for (int a = TX_START; a < TX_START + TX_COUNT; a++, first = 0)
        fprintf(fp, "%s\n    \"%d\": %u", first ? "" : ",", a, REG(a));
    for (int a = RX_START; a < RX_START + RX_COUNT; a++)
        fprintf(fp, ",\n    \"%d\": %u", a, REG(a));
    fprintf(fp, "\n  },\n  \"objects\": {");
    for (size_t i = 0; i < N_OBJECTS; i++) {
        const struct object *o = &objects[i];
        long long v;
        uint32_t u = (o->type == U32 || o->type == I32)
                         ? ((uint32_t)REG(o->reg) << 16) | REG(o->reg + 1)
                         : REG(o->reg);
        switch (o->type) {
        case I16: v = (int16_t)u; break;
        case I32: v = (int32_t)u; break;
        default: v = u; break;
        }
        fprintf(fp, "%s\n    \"%u\": {\"0\": %lld}", i ? "," : "", o->index, v);
    }
    fprintf(fp, "\n  },\n  \"diagnostic_counters\": {\"bus_message_count\": %u, "
                "\"bus_communication_error_count\": %u, \"bus_exception_error_count\": %u, "
                "\"slave_message_count\": %u, \"slave_no_response_count\": %u}\n}\n",
            cnt.bus_msg, cnt.bus_comm_err, cnt.bus_exc, cnt.slave_msg, cnt.slave_no_rsp);
    fflush(fp);
    fsync(fileno(fp));
    fclose(fp);
    rename(tmp, state_file);
}

/* ------------------------------------------------------------------ */
static void usage(void)
{
    fprintf(stderr, "usage: sim --serial DEVICE [--baud 19200] [--parity none|even|odd] "
                    "[--state FILE] [--slave 1]\n");
    exit(2);
}

int main(int argc, char **argv)
{
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (i + 1 >= argc)
            usage();
        const char *v = argv[++i];
        if (!strcmp(a, "--serial"))
            device = v;
        else if (!strcmp(a, "--baud"))
            baud = atoi(v);
        else if (!strcmp(a, "--state"))
            state_file = v;
        else if (!strcmp(a, "--slave"))
            slave_addr = atoi(v);
        else if (!strcmp(a, "--parity")) {
            if (!strcmp(v, "none") || !strcmp(v, "N") || !strcmp(v, "n"))
                parity_ch = 'N';
            else if (!strcmp(v, "even") || !strcmp(v, "E") || !strcmp(v, "e"))
                parity_ch = 'E';
            else if (!strcmp(v, "odd") || !strcmp(v, "O") || !strcmp(v, "o"))
                parity_ch = 'O';
            else
                usage();
        } else
            usage();
    }
    if (!device)
        usage();
    static const int bauds[] = {9600, 14400, 19200, 28800, 38400, 57600, 115200};
    int ok = 0;
    for (size_t i = 0; i < sizeof bauds / sizeof bauds[0]; i++)
        ok |= bauds[i] == baud;
    if (!ok || slave_addr < 1 || slave_addr > 247) {
        fprintf(stderr, "unsupported baud rate or slave address\n");
        return 2;
    }

    /* the manual: 8 data bits, 1 stop bit for every parity setting */
    ctx = modbus_new_rtu(device, baud, parity_ch, 8, 1);
    if (!ctx) {
        fprintf(stderr, "modbus_new_rtu: %s\n", modbus_strerror(errno));
        return 1;
    }
    modbus_set_slave(ctx, slave_addr);
    if (modbus_connect(ctx) == -1) {
        fprintf(stderr, "modbus_connect %s: %s\n", device, modbus_strerror(errno));
        modbus_free(ctx);
        return 1;
    }
    int fd = modbus_get_socket(ctx);

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigemptyset(&sa.sa_mask);
    sa.sa_flags = 0; /* no SA_RESTART: select() returns EINTR */
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGUSR1, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    last_tick = now_s();
    update_model(last_tick);

    /* t3.5: 3.5 characters of 11 bits, fixed 1.75 ms above 19200 Bd; we add a
     * floor of 4 ms because a pseudo terminal has scheduler jitter. */
    double t35 = baud > 19200 ? 0.00175 : 3.5 * 11.0 / baud;
    if (t35 < 0.004)
        t35 = 0.004;

    printf("listening serial %s\n", device);
    fflush(stdout);

    double last_rx = 0;
    int io_err = 0;
    while (!stop_flag) {
        if (dump_flag) {
            dump_flag = 0;
            dump_state();
        }
        double now = now_s();
        double wait = 0.010;
        if (rxlen > 0 || rx_overflow) {
            double left = last_rx + t35 - now;
            if (left <= 0) {
                end_of_frame();
                continue;
            }
            if (left < wait)
                wait = left;
        }
        if (io_err)
            wait = 0.050; /* peer gone: do not spin */
        fd_set rs;
        FD_ZERO(&rs);
        if (!io_err)
            FD_SET(fd, &rs);
        struct timeval tv = {0, (long)(wait * 1e6)};
        int rc = select(fd + 1, &rs, NULL, NULL, &tv);
        if (rc < 0) {
            if (errno == EINTR)
                continue;
            break;
        }
        if (rc > 0 && FD_ISSET(fd, &rs) && !io_err) {
            uint8_t tmp[256];
            ssize_t r = read(fd, tmp, sizeof tmp);
            if (r > 0) {
                last_rx = now_s();
                for (ssize_t i = 0; i < r; i++) {
                    if (rxlen < RXBUF)
                        rxb[rxlen++] = tmp[i];
                    else
                        rx_overflow = 1;
                }
                if (rxlen > MODBUS_RTU_MAX_ADU_LENGTH)
                    rx_overflow = 1;
                if (!rx_overflow)
                    try_complete();
            } else if (r == 0 || (errno != EAGAIN && errno != EINTR)) {
                io_err = 1;
            }
        } else if (io_err) {
            io_err = 0; /* retry reading after the pause */
        }
        update_model(now_s());
    }

    dump_state();
    modbus_close(ctx);
    modbus_free(ctx);
    return 0;
}

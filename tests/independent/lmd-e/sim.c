/*
 * Lexium MDrive (LMD) Ethernet, closed-loop (hMTechnology) model LMDCE572,
 * MODBUS/TCP server simulator built on libmodbus 3.1.6.
 *
 * Source: LMD MODBUS/TCP Fieldbus manual (LMD-MODBUS-REV-D).
 * See DECISIONS.md for the places where the manual is ambiguous or wrong
 * and for the places where libmodbus behaviour was kept or changed.
 *
 * Build: gcc -O2 -Wall -Wextra -o sim sim.c $(pkg-config --cflags --libs libmodbus)
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <time.h>
#include <unistd.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <arpa/inet.h>
#include <modbus.h>

/* ------------------------------------------------------------------ */
/* Exception codes                                                     */
#define EX_FUNC 0x01
#define EX_ADDR 0x02
#define EX_VAL  0x03
#define EX_FAIL 0x04
#define EX_BUSY 0x06

#define NREG 0xB8 /* 0x0000 .. 0x00B7 */

/* access classes */
enum { ACC_RW, ACC_RO, ACC_WO, ACC_CLR0 };
/* kinds */
enum { K_PARAM, K_DATA, K_STATUS, K_CMD };

typedef struct {
    uint16_t addr;
    uint8_t nregs;      /* 1 or 2 (2 = 32-bit, low word first) */
    const char *mn;     /* MCode mnemonic */
    uint8_t acc;
    uint8_t kind;
    int64_t min, max, def;
} item_t;

#define I32MIN (-2147483647LL - 1)
#define I32MAX 2147483647LL

static const item_t items[] = {
    {0x0000, 2, "A",  ACC_RW,  K_PARAM, 91, 1525878997, 1000000},
    {0x0004, 1, "BY", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x0005, 2, "C1", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x0007, 2, "C2", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x0009, 1, "CE", ACC_RW,  K_PARAM, 0, 1, 1},
    {0x000E, 1, "CW", ACC_RW,  K_PARAM, 0, 255, 10},
    {0x000F, 1, "D1", ACC_RW,  K_PARAM, 0, 255, 0},
    {0x0010, 1, "D2", ACC_RW,  K_PARAM, 0, 255, 0},
    {0x0011, 1, "D3", ACC_RW,  K_PARAM, 0, 255, 0},
    {0x0012, 1, "D4", ACC_RW,  K_PARAM, 0, 255, 0},
    {0x0013, 1, "D5", ACC_RW,  K_PARAM, 0, 255, 0},
    {0x0018, 2, "D",  ACC_RW,  K_PARAM, 91, 1525878997, 1000000},
    {0x001A, 1, "DB", ACC_RW,  K_PARAM, 0, 65000, 10},
    {0x001B, 1, "DC", ACC_WO,  K_CMD, 0, 65535, 0},
    {0x001C, 1, "DE", ACC_RW,  K_PARAM, 0, 1, 1},
    {0x001E, 1, "EE", ACC_RW,  K_PARAM, 0, 1, 0},
    {0x001F, 1, "EF", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x0021, 1, "ER", ACC_CLR0, K_DATA, 0, 65535, 0},
    {0x0024, 1, "FC", ACC_RW,  K_PARAM, 0, 9, 0},
    {0x0029, 1, "HC", ACC_RW,  K_PARAM, 0, 100, 5},
    {0x002A, 1, "HI", ACC_WO,  K_CMD, 1, 4, 0},
    {0x002B, 1, "HM", ACC_WO,  K_CMD, 1, 4, 0},
    {0x002C, 1, "HT", ACC_RW,  K_PARAM, 0, 65535, 500},
    {0x002D, 1, "I1", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x002E, 1, "I2", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x002F, 1, "I3", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x0030, 1, "I4", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x0031, 1, "I5", ACC_RO,  K_STATUS, 0, 1023, 0},
    {0x0032, 1, "I6", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x0037, 1, "IC", ACC_WO,  K_CMD, 0, 65535, 0},
    {0x003B, 1, "IN", ACC_RO,  K_STATUS, 0, 15, 0},
    {0x003C, 1, "IP", ACC_WO,  K_CMD, 0, 65535, 0},
    {0x003F, 1, "JE", ACC_RW,  K_PARAM, 0, 1, 0},
    {0x0042, 1, "LM", ACC_RW,  K_PARAM, 1, 6, 1},
    {0x0043, 2, "MA", ACC_WO,  K_CMD, I32MIN, I32MAX, 0},
    {0x0045, 1, "MP", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x0046, 2, "MR", ACC_WO,  K_CMD, I32MIN, I32MAX, 0},
    {0x0048, 1, "MS", ACC_RW,  K_PARAM, 1, 256, 256},
    {0x0049, 1, "MT", ACC_RW,  K_PARAM, 0, 65000, 0},
    {0x004A, 1, "MV", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x004B, 1, "O1", ACC_RW,  K_STATUS, 0, 1, 0},
    {0x004C, 1, "O2", ACC_RW,  K_STATUS, 0, 1, 0},
    {0x004D, 1, "O3", ACC_RW,  K_STATUS, 0, 1, 0},
    {0x004E, 1, "OF", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x0056, 1, "OT", ACC_RW,  K_STATUS, 0, 15, 0},
    {0x0057, 2, "P",  ACC_RW,  K_STATUS, I32MIN, I32MAX, 0},
    {0x0059, 2, "PC", ACC_RO,  K_DATA, I32MIN, I32MAX, 0},
    {0x005C, 1, "PM", ACC_RW,  K_PARAM, 0, 1, 0},
    {0x005F, 2, "R1", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x0061, 2, "R2", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x0063, 2, "R3", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x0065, 2, "R4", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x0067, 1, "RC", ACC_RW,  K_PARAM, 1, 100, 25},
    {0x0076, 1, "S",  ACC_WO,  K_CMD, 0, 65535, 0},
    {0x0077, 1, "SF", ACC_RW,  K_PARAM, 0, 65000, 15},
    {0x0078, 2, "SL", ACC_WO,  K_CMD, -5000000, 5000000, 0},
    {0x007A, 1, "SM", ACC_RW,  K_PARAM, 0, 1, 0},
    {0x007B, 1, "ST", ACC_CLR0, K_DATA, 0, 1, 0},
    {0x007D, 1, "TE", ACC_RW,  K_PARAM, 0, 43, 0},
    {0x0085, 2, "V",  ACC_RO,  K_STATUS, I32MIN, I32MAX, 0},
    {0x0088, 1, "VC", ACC_RO,  K_STATUS, 0, 1, 0},
    {0x0089, 2, "VI", ACC_RW,  K_PARAM, 1, 2559999, 1000},
    {0x008B, 2, "VM", ACC_RW,  K_PARAM, 2, 2560000, 768000},
    {0x008D, 1, "WT", ACC_RW,  K_PARAM, 0, 84, 80},
    {0x008E, 1, "AS", ACC_RW,  K_PARAM, 0, 3, 2},
    {0x008F, 1, "AF", ACC_RO,  K_STATUS, 0, 255, 0},
    {0x0091, 1, "CB", ACC_RW,  K_PARAM, 0, 3, 1},
    {0x0093, 1, "CF", ACC_WO,  K_CMD, 0, 65535, 0},
    {0x0095, 2, "LD", ACC_RW,  K_PARAM, 0, I32MAX, 102400},
    {0x0097, 2, "LG", ACC_RW,  K_PARAM, 0, I32MAX, 102400},
    {0x0099, 2, "LL", ACC_RO,  K_STATUS, -I32MAX, I32MAX, 0},
    {0x009B, 1, "LR", ACC_RO,  K_DATA, 0, 1, 0},
    {0x009C, 2, "LT", ACC_RW,  K_PARAM, 2, 65535, 2000},
    {0x009E, 2, "MF", ACC_RW,  K_PARAM, 306, 2560000, 768000},
    {0x00A0, 1, "MU", ACC_RW,  K_PARAM, 0, 2, 0},
    {0x00A1, 1, "SC", ACC_WO,  K_CMD, 0, 65535, 0},
    {0x00A3, 2, "TS", ACC_RW,  K_PARAM, 0, 255, 0},
    {0x00A5, 1, "TD", ACC_RW,  K_PARAM, 0, 1, 1},
    {0x00A6, 1, "TQ", ACC_RW,  K_PARAM, 1, 100, 25},
    {0x00A7, 1, "VF", ACC_RW,  K_PARAM, 0, 1000, 0},
    {0x00A8, 2, "V1", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x00AA, 2, "V2", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x00AC, 2, "V3", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x00AE, 2, "V4", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x00B0, 2, "V5", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x00B2, 2, "V6", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x00B4, 2, "V7", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
    {0x00B6, 2, "V8", ACC_RW,  K_DATA, I32MIN, I32MAX, 0},
};
#define NITEMS ((int)(sizeof(items) / sizeof(items[0])))

static int reg_item[NREG];   /* register address -> item index, -1 reserved */
static int64_t val[NITEMS];  /* stored values (params / data) */

static int idx_of(const char *mn)
{
    for (int i = 0; i < NITEMS; i++)
        if (strcmp(items[i].mn, mn) == 0) return i;
    return -1;
}
#define V(mn) val[idx_of(mn)]

/* ------------------------------------------------------------------ */
/* Vendor (FC 65/66) settings                                          */
typedef struct {
    int ao;             /* attention output mask 0..65535 */
    int pt_type[4];     /* I/O points 1..4: type */
    int pt_act[4];      /* active hi(1)/lo(0) */
    int pt_sink[4];     /* sinking(0)/sourcing(1) */
    int an_mode, an_range; /* analog input (point 5) */
    int mu_b;           /* make-up lead/lag option */
    int rd, aj, at, be, bm, dj, dt, fl;
    int64_t bl, fs;
    int ls_dir, ls_en; int64_t ls_pos;
    int64_t tr[3];
} vend_t;

static const vend_t vend_default = {
    0, {0, 0, 0, 0}, {0, 0, 0, 0}, {0, 0, 0, 0}, 9, 0, 0,
    0, 128, 0, 0, 0, 128, 0, 0, 0, 0, 0, 0, 0, {0, 0, 0}
};
static vend_t vend;

/* NVM image (written by S / Save) */
static int64_t nvm_val[NITEMS];
static vend_t nvm_vend;

/* Output latches of points 1..4 (used when the point is a GP output) */
static int out_latch[4];

/* Program state: no MCode program can be downloaded over MODBUS/TCP. */
static int program_loaded = 0;
static int upgrade_mode = 0;

/* Motion */
enum { M_IDLE, M_POINT, M_SLEW, M_HOME };
static struct {
    int mode;
    double pos, vel, target, slew_v;
    double c2acc;
    int vel_changing;
    double home_min_end;
    double calib_end;
} mo;

/* diagnostic counters */
static struct {
    unsigned long frames, exceptions, dropped, connections, bad_framing;
} diag;

static const char *serial_no = "269130001";

/* small helpers so that the program links without libm */
static double fabs_(double x) { return x < 0 ? -x : x; }
static double fmin_(double a, double b) { return a < b ? a : b; }
static double fmax_(double a, double b) { return a > b ? a : b; }
static long long lround_(double x) { return x >= 0 ? (long long)(x + 0.5) : -(long long)(-x + 0.5); }

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec / 1e9;
}

static void set_factory(void)
{
    for (int i = 0; i < NITEMS; i++)
        if (items[i].kind == K_PARAM) val[i] = items[i].def;
    vend = vend_default;
}

static void init_state(void)
{
    for (int a = 0; a < NREG; a++) reg_item[a] = -1;
    for (int i = 0; i < NITEMS; i++) {
        for (int k = 0; k < items[i].nregs; k++) reg_item[items[i].addr + k] = i;
        val[i] = items[i].def;
    }
    vend = vend_default;
    memcpy(nvm_val, val, sizeof(val));
    nvm_vend = vend;
    memset(&mo, 0, sizeof(mo));
}

/* ------------------------------------------------------------------ */
/* Motion simulation                                                   */
static int is_moving(void) { return mo.mode != M_IDLE || mo.vel != 0.0; }

static long long last_ipos = 0; /* last integer step position seen by the pulse counters */

static void move_pos(double d)
{
    mo.pos += d;
    long long ip = lround_(mo.pos);
    long long delta = ip - last_ipos;
    last_ipos = ip;
    if (delta == 0) return;
    V("C1") += delta;
    /* internal encoder: 4096 counts per revolution (200 full steps * MS) */
    mo.c2acc += (double)delta * 4096.0 / (200.0 * (double)V("MS"));
    long long c2 = (long long)mo.c2acc; /* truncate toward zero */
    V("C2") += c2;
    mo.c2acc -= (double)c2;
    /* keep counters in int32 range (wrap) */
    if (V("C1") > I32MAX) V("C1") -= 4294967296LL;
    if (V("C1") < I32MIN) V("C1") += 4294967296LL;
    if (V("C2") > I32MAX) V("C2") -= 4294967296LL;
    if (V("C2") < I32MIN) V("C2") += 4294967296LL;
    if (mo.pos > (double)I32MAX) { mo.pos -= 4294967296.0; last_ipos = lround_(mo.pos); }
    if (mo.pos < (double)I32MIN) { mo.pos += 4294967296.0; last_ipos = lround_(mo.pos); }
}

static void stop_now(void)
{
    mo.mode = M_IDLE;
    mo.vel = 0.0;
    mo.vel_changing = 0;
    mo.pos = (double)lround_(mo.pos);
}

static void step_motion(double dt, double tnow)
{
    double A = (double)V("A"), D = (double)V("D");
    double VM = (double)V("VM"), VI = (double)V("VI");
    double v0 = mo.vel;
    switch (mo.mode) {
    case M_IDLE:
        break;
    case M_SLEW: {
        double tv = mo.slew_v;
        double dv;
        if (tv == 0.0 || (mo.vel != 0.0 && (tv > 0) != (mo.vel > 0)) || fabs_(tv) < fabs_(mo.vel)) {
            dv = D * dt; /* decelerate */
        } else {
            dv = A * dt;
            if (mo.vel == 0.0) mo.vel = (tv > 0 ? 1 : -1) * fmin_(VI, fabs_(tv));
        }
        if (mo.vel < tv) mo.vel = fmin_(mo.vel + dv, tv);
        else if (mo.vel > tv) mo.vel = fmax_(mo.vel - dv, tv);
        if (mo.vel != 0.0 && tv != 0.0 && (tv > 0) != (mo.vel > 0) && fabs_(mo.vel) < 1) mo.vel = 0;
        move_pos(mo.vel * dt);
        if (tv == 0.0 && mo.vel == 0.0) stop_now();
        break;
    }
    case M_POINT:
    case M_HOME: {
        double rem = mo.target - mo.pos;
        double dir = rem >= 0 ? 1.0 : -1.0;
        double sp = fabs_(mo.vel);
        if (mo.vel != 0.0 && (mo.vel > 0) != (dir > 0)) {
            sp = fmax_(sp - D * dt, 0.0);
            mo.vel = (mo.vel > 0 ? 1 : -1) * sp;
            move_pos(mo.vel * dt);
            break;
        }
        double stopd = sp * sp / (2.0 * D);
        if (fabs_(rem) <= stopd + sp * dt) {
            sp = fmax_(sp - D * dt, fmin_(VI, VM) * 0.5);
        } else {
            if (sp < VI) sp = fmin_(VI, VM);
            sp = fmin_(sp + A * dt, VM);
        }
        double st = sp * dt;
        if (st >= fabs_(rem)) {
            move_pos(rem);
            mo.pos = mo.target;
            mo.vel = 0.0;
            if (mo.mode == M_HOME) {
                if (tnow < mo.home_min_end) { mo.vel_changing = 0; return; }
                mo.pos = 0.0; /* home position is the new origin */
                last_ipos = 0;
                mo.c2acc = 0.0;
            }
            stop_now();
        } else {
            mo.vel = dir * sp;
            move_pos(dir * st);
        }
        break;
    }
    }
    mo.vel_changing = (mo.vel != v0) && mo.mode != M_IDLE;
}

static double last_tick = 0.0;
static void update_motion(void)
{
    double t = now_s();
    double dt = t - last_tick;
    last_tick = t;
    if (dt <= 0) return;
    if (dt > 1.0) dt = 1.0;
    while (dt > 0) {
        double h = dt > 0.002 ? 0.002 : dt;
        step_motion(h, t);
        dt -= h;
    }
}

/* ------------------------------------------------------------------ */
/* I/O points                                                          */
static int is_input_type(int t)
{
    return t == 0 || t == 1 || t == 2 || t == 3 || t == 5 || t == 7 || t == 8 || t == 11 || t == 12;
}
static int is_output_type(int t)
{
    return t == 16 || t == 17 || t == 18 || t == 20 || t == 21 || t == 23 || t == 24 || t == 25 ||
           t == 28 || t == 29;
}

static int af_value(void)
{
    int af = 0;
    if (V("AS") != 0) af |= 16;
    if (!is_moving()) af |= 64;
    if (now_s() >= mo.calib_end) af |= 128;
    if (V("LR")) af |= 8;
    return af;
}

static int point_level(int i)
{
    int t = vend.pt_type[i];
    if (!is_output_type(t)) return 0; /* inputs: nothing wired in the simulator */
    switch (t) {
    case 16: return out_latch[i];
    case 17: return is_moving();
    case 18: return V("ER") != 0;
    case 20: return mo.vel_changing;
    case 21: return (int)V("LR");
    case 23: return mo.mode == M_POINT || mo.mode == M_HOME;
    case 24: return V("AS") != 0;
    case 29: {
        int cond = 0;
        if (V("ER") != 0) cond |= 1;
        if (V("LR")) cond |= 2;
        if (V("AS") != 0) cond |= 16;
        if (now_s() < mo.calib_end) cond |= 32;
        if (V("DE") == 0) cond |= 2048;
        if (is_moving()) cond |= 16384;
        if (V("ST")) cond |= 32768;
        return (vend.ao & cond) != 0;
    }
    default: return 0;
    }
}

/* Current value of an item as the client reads it */
static int64_t get_item(int i)
{
    const char *m = items[i].mn;
    if (items[i].kind != K_STATUS) {
        if (!strcmp(m, "ER")) return val[i];
        return val[i];
    }
    if (!strcmp(m, "BY")) return 0; /* no program can be running */
    if (!strcmp(m, "EF")) return V("ER") != 0;
    if (m[0] == 'I' && m[1] >= '1' && m[1] <= '4') return point_level(m[1] - '1');
    if (!strcmp(m, "I5")) return 0;
    if (!strcmp(m, "I6")) return 0;
    if (!strcmp(m, "IN")) {
        int v = 0;
        for (int k = 0; k < 4; k++) v |= point_level(k) << k;
        return v;
    }
    if (!strcmp(m, "MP")) return mo.mode == M_POINT || mo.mode == M_HOME;
    if (!strcmp(m, "MV")) return is_moving();
    if (m[0] == 'O' && m[1] >= '1' && m[1] <= '3') return point_level(m[1] - '1');
    if (!strcmp(m, "OF")) return 0;
    if (!strcmp(m, "OT")) {
        int v = 0;
        for (int k = 0; k < 4; k++) v |= point_level(k) << k;
        return v;
    }
    if (!strcmp(m, "P")) return (int64_t)lround_(mo.pos);
    if (!strcmp(m, "V")) return (int64_t)lround_(mo.vel);
    if (!strcmp(m, "VC")) return mo.vel_changing;
    if (!strcmp(m, "AF")) return af_value();
    if (!strcmp(m, "LL")) return 0;
    return 0;
}

static uint16_t reg_word(int addr)
{
    int i = reg_item[addr];
    int64_t v = get_item(i);
    uint32_t u = (uint32_t)(int32_t)v;
    if (items[i].nregs == 1) return (uint16_t)(u & 0xFFFF);
    return (addr == items[i].addr) ? (uint16_t)(u & 0xFFFF) : (uint16_t)(u >> 16);
}

/* ------------------------------------------------------------------ */
/* Register writes                                                     */
static int moving_cmd_check(void)
{
    if (V("DE") == 0) return EX_FAIL; /* bridge disabled: motion refused */
    return 0;
}

/* check one item write; returns 0 or exception */
static int check_item_write(int i, int64_t v)
{
    const item_t *it = &items[i];
    const char *m = it->mn;
    if (it->acc == ACC_RO) return EX_ADDR;
    if (it->acc == ACC_CLR0) return v == 0 ? 0 : EX_VAL;
    if (v < it->min || v > it->max) return EX_VAL;
    if (!strcmp(m, "MS")) {
        static const int ok[] = {1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127};
        int f = 0;
        for (unsigned k = 0; k < sizeof(ok) / sizeof(ok[0]); k++) if (ok[k] == v) f = 1;
        if (!f) return EX_VAL;
        if (is_moving()) return EX_BUSY;
    }
    if (!strcmp(m, "HT")) {
        if (v == 1) return EX_VAL;
        if (v + V("MT") > 65535) return EX_VAL;
    }
    if (!strcmp(m, "MT") && v + V("HT") > 65535) return EX_VAL;
    if (!strcmp(m, "VI") && v >= V("VM")) return EX_VAL;
    if (!strcmp(m, "VM") && v <= V("VI")) return EX_VAL;
    if (!strcmp(m, "DC") || !strcmp(m, "IC")) {
        int t = (v >= 0 && v < NREG) ? reg_item[v] : -1;
        if (t < 0 || items[t].addr != v || items[t].kind != K_DATA || items[t].nregs != 2 ||
            items[t].acc != ACC_RW)
            return EX_VAL;
    }
    if (m[0] == 'O' && m[1] >= '1' && m[1] <= '3' && m[2] == 0) {
        int p = m[1] - '1';
        if (v > 1) return EX_VAL;
        if (vend.pt_type[p] != 16) return EX_FAIL;
    }
    if (!strcmp(m, "OT")) {
        for (int k = 0; k < 4; k++)
            if (vend.pt_type[k] != 16 && ((v >> k) & 1) != point_level(k)) return EX_FAIL;
    }
    if (!strcmp(m, "MA") || !strcmp(m, "MR") || !strcmp(m, "SL") || !strcmp(m, "HM") || !strcmp(m, "HI"))
        return moving_cmd_check();
    if (!strcmp(m, "P") && is_moving()) return EX_BUSY;
    if (!strcmp(m, "IP") && is_moving()) return EX_BUSY;
    return 0;
}

static void start_home(void)
{
    mo.mode = M_HOME;
    mo.target = 0.0;
    mo.home_min_end = now_s() + 0.3;
}

static void apply_item_write(int i, int64_t v)
{
    const char *m = items[i].mn;
    if (!strcmp(m, "MA")) { mo.mode = M_POINT; mo.target = (double)v; return; }
    if (!strcmp(m, "MR")) {
        double t = (mo.mode == M_POINT ? mo.target : (double)lround_(mo.pos)) + (double)v;
        mo.mode = M_POINT; mo.target = t; return;
    }
    if (!strcmp(m, "SL")) {
        if (v == 0 && !is_moving()) return;
        mo.mode = M_SLEW; mo.slew_v = (double)v; return;
    }
    if (!strcmp(m, "HM") || !strcmp(m, "HI")) { start_home(); return; }
    if (!strcmp(m, "P")) { mo.pos = (double)v; last_ipos = v; mo.c2acc = 0.0; return; }
    if (!strcmp(m, "DC") || !strcmp(m, "IC")) {
        int t = reg_item[v];
        int64_t nv = val[t] + (m[0] == 'D' ? -1 : 1);
        if (nv > I32MAX) nv = I32MIN;
        if (nv < I32MIN) nv = I32MAX;
        val[t] = nv;
        return;
    }
    if (!strcmp(m, "IP")) { set_factory(); return; }
    if (!strcmp(m, "S")) { memcpy(nvm_val, val, sizeof(val)); nvm_vend = vend; return; }
    if (!strcmp(m, "CF")) { V("LR") = 0; mo.calib_end = now_s() + 0.5; return; }
    if (!strcmp(m, "SC")) { mo.calib_end = now_s() + 0.5; return; }
    if (!strcmp(m, "ER")) { val[i] = 0; return; }
    if (m[0] == 'O' && m[1] >= '1' && m[1] <= '3' && m[2] == 0) { out_latch[m[1] - '1'] = (int)v; return; }
    if (!strcmp(m, "OT")) {
        for (int k = 0; k < 4; k++) if (vend.pt_type[k] == 16) out_latch[k] = (v >> k) & 1;
        return;
    }
    if (!strcmp(m, "DE") && v == 0) stop_now();
    if (!strcmp(m, "MU")) { val[i] = v; return; }
    val[i] = v;
}

/* ------------------------------------------------------------------ */
/* Networking                                                          */
static modbus_t *ctx;
static modbus_mapping_t *map;

static volatile sig_atomic_t g_quit = 0, g_dump = 0;
static const char *state_file = NULL;

static void on_term(int s) { (void)s; g_quit = 1; }
static void on_usr1(int s) { (void)s; g_dump = 1; }

static int send_raw(int fd, const uint8_t *req, const uint8_t *pdu, int pdu_len)
{
    uint8_t out[300];
    out[0] = req[0]; out[1] = req[1];
    out[2] = 0; out[3] = 0;
    out[4] = (uint8_t)((pdu_len + 1) >> 8);
    out[5] = (uint8_t)((pdu_len + 1) & 0xFF);
    out[6] = req[6];
    memcpy(out + 7, pdu, pdu_len);
    ssize_t n = send(fd, out, 7 + pdu_len, MSG_NOSIGNAL);
    return n == 7 + pdu_len ? 0 : -1;
}

static int reply_exc(const uint8_t *req, int code)
{
    diag.exceptions++;
    return modbus_reply_exception(ctx, req, code);
}

/* --- FC 0x2B / 0x0E -------------------------------------------------- */
static const char *devid_obj(int id)
{
    switch (id) {
    case 0: return "IMS USA";
    case 1: return "LMDCE572";
    case 2: return "4.0.0.0";
    case 3: return "https://novantaims.com/";
    case 4: return "LMD Ethernet";
    case 5: return serial_no;
    case 6: return "LMDCM 6.010, Hw: 1.0";
    }
    return NULL;
}

static int handle_devid(int fd, const uint8_t *req, const uint8_t *pdu, int plen)
{
    if (plen < 2) return reply_exc(req, EX_VAL);
    if (pdu[1] != 0x0E) return reply_exc(req, EX_FUNC);
    if (plen != 4) return reply_exc(req, EX_VAL);
    int code = pdu[2], obj = pdu[3];
    if (code < 1 || code > 4) return reply_exc(req, EX_VAL);
    uint8_t out[260];
    int n = 0;
    out[n++] = 0x2B; out[n++] = 0x0E; out[n++] = (uint8_t)code; out[n++] = 0x82;
    out[n++] = 0; out[n++] = 0; out[n++] = 0;
    int first, last;
    if (code == 4) {
        if (obj > 6) return reply_exc(req, EX_ADDR);
        first = last = obj;
    } else {
        last = (code == 1) ? 2 : 6;
        first = (obj > last) ? 0 : obj;
    }
    int cnt = 0;
    for (int id = first; id <= last; id++) {
        const char *s = devid_obj(id);
        int l = (int)strlen(s);
        out[n++] = (uint8_t)id; out[n++] = (uint8_t)l;
        memcpy(out + n, s, l); n += l; cnt++;
    }
    out[6] = (uint8_t)cnt;
    return send_raw(fd, req, out, n);
}

/* --- FC 0x41 / 0x42 -------------------------------------------------- */
static void mnem_decode(const uint8_t *m, char *out)
{
    char t[5];
    t[0] = (char)m[3]; t[1] = (char)m[2]; t[2] = (char)m[1]; t[3] = (char)m[0]; t[4] = 0;
    int s = 0, e = 4;
    while (s < e && (t[s] == ' ' || t[s] == 0)) s++;
    while (e > s && (t[e - 1] == ' ' || t[e - 1] == 0)) e--;
    memcpy(out, t + s, e - s);
    out[e - s] = 0;
}

/* parse "=a,b,c" (spaces tolerated around items) */
static int parse_params(const uint8_t *d, int len, int64_t *out, int maxn)
{
    char buf[64];
    if (len <= 0 || len >= (int)sizeof(buf)) return -1;
    memcpy(buf, d, len); buf[len] = 0;
    for (int k = 0; k < len; k++) if (buf[k] == 0) return -1;
    char *p = buf;
    while (*p == ' ') p++;
    if (*p != '=') return -1;
    p++;
    int n = 0;
    for (;;) {
        while (*p == ' ') p++;
        char *st = p;
        if (*p == '+' || *p == '-') p++;
        if (*p < '0' || *p > '9') return -1;
        int nd = 0;
        while (*p >= '0' && *p <= '9') { p++; nd++; }
        if (nd > 10) return -1;
        if (n >= maxn) return -1;
        out[n++] = strtoll(st, NULL, 10);
        while (*p == ' ') p++;
        if (*p == ',') { p++; continue; }
        if (*p == 0) break;
        return -1;
    }
    return n;
}

enum { VA_R = 1, VA_W = 2, VA_RW = 3 };
static const struct { const char *mn; int acc; } vitems[] = {
    {"\x1b", VA_W}, {"AO", VA_RW}, {"CP", VA_W}, {"EL", VA_R}, {"EX", VA_W},
    {"IS", VA_RW}, {"OS", VA_RW}, {"S1", VA_RW}, {"S2", VA_RW}, {"S3", VA_RW}, {"S4", VA_RW},
    {"S5", VA_RW}, {"IT", VA_R}, {"MU", VA_RW}, {"PS", VA_W}, {"RS", VA_W}, {"E", VA_W},
    {"RD", VA_RW}, {"AJ", VA_RW}, {"AT", VA_RW}, {"BE", VA_RW}, {"BL", VA_RW}, {"BM", VA_RW},
    {"DJ", VA_RW}, {"DT", VA_RW}, {"FS", VA_RW}, {"HF", VA_W}, {"AV", VA_R}, {"FL", VA_RW},
    {"LS", VA_RW}, {"UG", VA_W}, {"VT", VA_R}, {"TR", VA_RW},
};

static int vend_read(const char *mn, char *o, int osz)
{
    if (!strcmp(mn, "AO")) return snprintf(o, osz, "%d", vend.ao);
    if (!strcmp(mn, "EL")) return snprintf(o, osz, "1000");
    if (mn[0] == 'S' && mn[1] >= '1' && mn[1] <= '4') {
        int p = mn[1] - '1';
        return snprintf(o, osz, "%d,%d,%d", vend.pt_type[p], vend.pt_act[p], vend.pt_sink[p]);
    }
    if (!strcmp(mn, "S5")) return snprintf(o, osz, "%d,%d", vend.an_mode, vend.an_range);
    if (!strcmp(mn, "IS"))
        return snprintf(o, osz, "1,%d,%d;2,%d,%d;3,%d,%d;4,%d,%d;5,%d,%d", vend.pt_type[0], vend.pt_act[0],
                        vend.pt_type[1], vend.pt_act[1], vend.pt_type[2], vend.pt_act[2], vend.pt_type[3],
                        vend.pt_act[3], vend.an_mode, vend.an_range);
    if (!strcmp(mn, "OS"))
        return snprintf(o, osz, "1,%d,%d;2,%d,%d;3,%d,%d", vend.pt_type[0], vend.pt_act[0], vend.pt_type[1],
                        vend.pt_act[1], vend.pt_type[2], vend.pt_act[2]);
    if (!strcmp(mn, "IT")) return snprintf(o, osz, "38,41");
    if (!strcmp(mn, "VT")) return snprintf(o, osz, "24,48");
    if (!strcmp(mn, "MU")) return snprintf(o, osz, "%d,%d", (int)V("MU"), vend.mu_b);
    if (!strcmp(mn, "RD")) return snprintf(o, osz, "%d", vend.rd);
    if (!strcmp(mn, "AJ")) return snprintf(o, osz, "%d", vend.aj);
    if (!strcmp(mn, "AT")) return snprintf(o, osz, "%d", vend.at);
    if (!strcmp(mn, "BE")) return snprintf(o, osz, "%d", vend.be);
    if (!strcmp(mn, "BL")) return snprintf(o, osz, "%lld", (long long)vend.bl);
    if (!strcmp(mn, "BM")) return snprintf(o, osz, "%d", vend.bm);
    if (!strcmp(mn, "DJ")) return snprintf(o, osz, "%d", vend.dj);
    if (!strcmp(mn, "DT")) return snprintf(o, osz, "%d", vend.dt);
    if (!strcmp(mn, "FS")) return snprintf(o, osz, "%lld", (long long)vend.fs);
    if (!strcmp(mn, "AV")) return snprintf(o, osz, "%lld", (long long)lround_(fabs_(mo.vel)));
    if (!strcmp(mn, "FL")) return snprintf(o, osz, "%d", vend.fl);
    if (!strcmp(mn, "LS")) return snprintf(o, osz, "%d,%lld,%d", vend.ls_dir, (long long)vend.ls_pos, vend.ls_en);
    if (!strcmp(mn, "TR"))
        return snprintf(o, osz, "%lld, %lld, %lld", (long long)vend.tr[0], (long long)vend.tr[1],
                        (long long)vend.tr[2]);
    return -1;
}

static int set_point(int p, int type, int act, int sink)
{
    if (!(act == 0 || act == 1) || !(sink == 0 || sink == 1)) return EX_VAL;
    if (is_input_type(type)) {
        /* ok */
    } else if (is_output_type(type)) {
        if (p > 2) return EX_VAL;           /* outputs only on points 1-3 */
        if (type == 28 && p != 2) return EX_VAL; /* trip: output 3 only */
    } else {
        return EX_VAL;
    }
    vend.pt_type[p] = type; vend.pt_act[p] = act; vend.pt_sink[p] = sink;
    if (type != 16) out_latch[p] = 0;
    return 0;
}

static int bin01(int64_t v) { return v == 0 || v == 1; }

/* returns 0 on success or exception code */
static int vend_write(const char *mn, const uint8_t *d, int n)
{
    int64_t a[4];
    int k;
    /* commands with no parameter data */
    if (!strcmp(mn, "\x1b") || !strcmp(mn, "CP") || !strcmp(mn, "PS") || !strcmp(mn, "RS") || !strcmp(mn, "E")) {
        if (n != 0) return EX_VAL;
        if (mn[0] == 0x1b) stop_now();
        if (!strcmp(mn, "CP")) program_loaded = 0;
        return 0;
    }
    if (!strcmp(mn, "EX")) {
        /* " G1" style label, or a numeric address */
        char b[8];
        if (n < 1 || n > 4) return EX_VAL;
        memcpy(b, d, n); b[n] = 0;
        char *p = b;
        while (*p == ' ') p++;
        int l = (int)strlen(p);
        if (l < 1) return EX_VAL;
        for (int q = 0; q < l; q++)
            if (!((p[q] >= 'A' && p[q] <= 'Z') || (p[q] >= '0' && p[q] <= '9'))) return EX_VAL;
        if (!program_loaded) return EX_FAIL; /* nothing stored to execute */
        return 0;
    }
    if (!strcmp(mn, "UG")) {
        if (n != 8 || memcmp(d, " 2956102", 8) != 0) return EX_VAL;
        if (is_moving()) return EX_BUSY;
        upgrade_mode = 1;
        return 0;
    }
    k = parse_params(d, n, a, 4);
    if (k < 0) return EX_VAL;
    if (!strcmp(mn, "AO")) {
        if (k != 1 || a[0] < 0 || a[0] > 65535) return EX_VAL;
        vend.ao = (int)a[0]; return 0;
    }
    if (mn[0] == 'S' && mn[1] >= '1' && mn[1] <= '4') {
        if (k != 3) return EX_VAL;
        return set_point(mn[1] - '1', (int)a[0], (int)a[1], (int)a[2]);
    }
    if (!strcmp(mn, "S5")) {
        if (k != 2 || !(a[0] == 9 || a[0] == 10) || !bin01(a[1])) return EX_VAL;
        vend.an_mode = (int)a[0]; vend.an_range = (int)a[1]; return 0;
    }
    if (!strcmp(mn, "IS")) {
        if (k != 3 || a[0] < 1 || a[0] > 5) return EX_VAL;
        if (a[0] == 5) {
            if (!(a[1] == 9 || a[1] == 10) || !bin01(a[2])) return EX_VAL;
            vend.an_mode = (int)a[1]; vend.an_range = (int)a[2]; return 0;
        }
        if (!is_input_type((int)a[1])) return EX_VAL;
        return set_point((int)a[0] - 1, (int)a[1], (int)a[2], vend.pt_sink[a[0] - 1]);
    }
    if (!strcmp(mn, "OS")) {
        if (k != 3 || a[0] < 1 || a[0] > 3 || !is_output_type((int)a[1])) return EX_VAL;
        return set_point((int)a[0] - 1, (int)a[1], (int)a[2], vend.pt_sink[a[0] - 1]);
    }
    if (!strcmp(mn, "MU")) {
        if (k != 2 || a[0] < 0 || a[0] > 2 || !bin01(a[1])) return EX_VAL;
        V("MU") = a[0]; vend.mu_b = (int)a[1]; return 0;
    }
    if (k != 1 && strcmp(mn, "LS") && strcmp(mn, "TR")) return EX_VAL;
    if (!strcmp(mn, "RD")) { if (!bin01(a[0])) return EX_VAL; if (is_moving()) return EX_BUSY; vend.rd = (int)a[0]; return 0; }
    if (!strcmp(mn, "BE")) { if (!bin01(a[0])) return EX_VAL; vend.be = (int)a[0]; return 0; }
    if (!strcmp(mn, "BM")) { if (!bin01(a[0])) return EX_VAL; vend.bm = (int)a[0]; return 0; }
    if (!strcmp(mn, "FL")) { if (!bin01(a[0])) return EX_VAL; vend.fl = (int)a[0]; return 0; }
    if (!strcmp(mn, "AT")) { if (!bin01(a[0])) return EX_VAL; vend.at = (int)a[0]; return 0; }
    if (!strcmp(mn, "DT")) { if (!bin01(a[0])) return EX_VAL; vend.dt = (int)a[0]; return 0; }
    if (!strcmp(mn, "AJ")) { if (a[0] < 1 || a[0] > 999) return EX_VAL; vend.aj = (int)a[0]; return 0; }
    if (!strcmp(mn, "DJ")) { if (a[0] < 1 || a[0] > 999) return EX_VAL; vend.dj = (int)a[0]; return 0; }
    if (!strcmp(mn, "BL")) { if (a[0] < 0 || a[0] > I32MAX) return EX_VAL; vend.bl = a[0]; return 0; }
    if (!strcmp(mn, "FS")) { if (a[0] < 0 || a[0] > 99999) return EX_VAL; vend.fs = a[0]; return 0; }
    if (!strcmp(mn, "HF")) {
        if (!bin01(a[0])) return EX_VAL;
        int e = moving_cmd_check();
        if (e) return e;
        start_home();
        return 0;
    }
    if (!strcmp(mn, "LS")) {
        if (k != 3 || !bin01(a[0]) || !bin01(a[2]) || a[1] < I32MIN || a[1] > I32MAX) return EX_VAL;
        vend.ls_dir = (int)a[0]; vend.ls_pos = a[1]; vend.ls_en = (int)a[2]; return 0;
    }
    if (!strcmp(mn, "TR")) {
        if (k != 3) return EX_VAL;
        for (int q = 0; q < 3; q++) if (a[q] < I32MIN || a[q] > I32MAX) return EX_VAL;
        for (int q = 0; q < 3; q++) vend.tr[q] = a[q];
        return 0;
    }
    return EX_ADDR;
}

static int handle_mfg(int fd, const uint8_t *req, const uint8_t *pdu, int plen)
{
    int fc = pdu[0];
    if (plen < 5) return reply_exc(req, EX_VAL);
    if (fc == 0x41 && plen != 5) return reply_exc(req, EX_VAL);
    if (fc == 0x42) {
        if (plen < 6 || pdu[5] != plen - 6 || pdu[5] > 28) return reply_exc(req, EX_VAL);
    }
    char mn[5];
    mnem_decode(pdu + 1, mn);
    int acc = 0;
    for (unsigned k = 0; k < sizeof(vitems) / sizeof(vitems[0]); k++)
        if (!strcmp(vitems[k].mn, mn)) acc = vitems[k].acc;
    if (!acc) return reply_exc(req, EX_ADDR);
    uint8_t out[260];
    if (fc == 0x41) {
        if (!(acc & VA_R)) return reply_exc(req, EX_ADDR);
        char s[200];
        int l = vend_read(mn, s, sizeof(s));
        if (l < 0) return reply_exc(req, EX_FAIL);
        out[0] = 0x41; out[1] = (uint8_t)l;
        memcpy(out + 2, s, l);
        return send_raw(fd, req, out, 2 + l);
    }
    if (!(acc & VA_W)) return reply_exc(req, EX_ADDR);
    int e = vend_write(mn, pdu + 6, pdu[5]);
    if (e) return reply_exc(req, e);
    out[0] = 0x42; out[1] = pdu[5];
    memcpy(out + 2, pdu + 1, 4);
    return send_raw(fd, req, out, 6);
}

/* --- standard function codes --------------------------------------- */
static void fill_bits(void)
{
    for (int k = 0; k < 4; k++) {
        int l = point_level(k);
        map->tab_bits[k] = (uint8_t)l;
        map->tab_input_bits[k] = (uint8_t)l;
    }
}

static int handle_std(const uint8_t *req, int adu_len, const uint8_t *pdu, int plen)
{
    int fc = pdu[0];
    int rc;
    switch (fc) {
    case 0x01:
    case 0x02: {
        if (plen != 5) return reply_exc(req, EX_VAL);
        int nb = (pdu[3] << 8) | pdu[4];
        if (nb < 1 || nb > MODBUS_MAX_READ_BITS) return reply_exc(req, EX_VAL);
        fill_bits();
        return modbus_reply(ctx, req, adu_len, map);
    }
    case 0x05: {
        if (plen != 5) return reply_exc(req, EX_VAL);
        int addr = (pdu[1] << 8) | pdu[2];
        int v = (pdu[3] << 8) | pdu[4];
        if (addr > 3) return reply_exc(req, EX_ADDR); /* library order: address, then value */
        if (v != 0 && v != 0xFF00) return reply_exc(req, EX_VAL);
        if (vend.pt_type[addr] != 16) return reply_exc(req, EX_FAIL);
        fill_bits();
        rc = modbus_reply(ctx, req, adu_len, map);
        out_latch[addr] = map->tab_bits[addr] ? 1 : 0;
        return rc;
    }
    case 0x03: {
        if (plen != 5) return reply_exc(req, EX_VAL);
        int addr = (pdu[1] << 8) | pdu[2];
        int nb = (pdu[3] << 8) | pdu[4];
        if (nb < 1 || nb > 2) return reply_exc(req, EX_VAL);
        if (addr + nb > NREG) return reply_exc(req, EX_ADDR);
        for (int a = addr; a < addr + nb; a++) {
            int i = reg_item[a];
            if (i < 0 || items[i].acc == ACC_WO) return reply_exc(req, EX_ADDR);
        }
        for (int a = addr; a < addr + nb; a++) map->tab_registers[a] = reg_word(a);
        rc = modbus_reply(ctx, req, adu_len, map);
        /* ER is cleared by reading it */
        for (int a = addr; a < addr + nb; a++)
            if (reg_item[a] == idx_of("ER")) V("ER") = 0;
        return rc;
    }
    case 0x10: {
        if (plen < 6) return reply_exc(req, EX_VAL);
        int addr = (pdu[1] << 8) | pdu[2];
        int nb = (pdu[3] << 8) | pdu[4];
        int bc = pdu[5];
        if (nb < 1 || nb > 2 || bc != nb * 2 || plen != 6 + bc) return reply_exc(req, EX_VAL);
        if (addr + nb > NREG) return reply_exc(req, EX_ADDR);
        /* address / item alignment checks */
        int it[2], ni = 0;
        for (int a = addr; a < addr + nb;) {
            int i = reg_item[a];
            if (i < 0 || items[i].addr != a || a + items[i].nregs > addr + nb) return reply_exc(req, EX_ADDR);
            if (items[i].acc == ACC_RO) return reply_exc(req, EX_ADDR);
            it[ni++] = i;
            a += items[i].nregs;
        }
        int64_t vv[2];
        for (int k = 0, off = 6; k < ni; k++) {
            const item_t *x = &items[it[k]];
            if (x->nregs == 1) {
                vv[k] = (pdu[off] << 8) | pdu[off + 1];
                off += 2;
            } else {
                uint32_t lo = (pdu[off] << 8) | pdu[off + 1];
                uint32_t hi = (pdu[off + 2] << 8) | pdu[off + 3];
                vv[k] = (int32_t)((hi << 16) | lo);
                off += 4;
            }
        }
        for (int k = 0; k < ni; k++) {
            int e = check_item_write(it[k], vv[k]);
            if (e) return reply_exc(req, e);
        }
        rc = modbus_reply(ctx, req, adu_len, map);
        for (int k = 0; k < ni; k++) apply_item_write(it[k], vv[k]);
        return rc;
    }
    }
    return reply_exc(req, EX_FUNC);
}

/* Process one complete ADU. Returns -1 if the connection should close. */
static int process_adu(int fd, const uint8_t *adu, int len)
{
    diag.frames++;
    const uint8_t *pdu = adu + 7;
    int plen = len - 7;
    int fc = pdu[0];
    int rc;
    update_motion();
    modbus_set_socket(ctx, fd);
    if (fc == 0x01 || fc == 0x02 || fc == 0x03 || fc == 0x05 || fc == 0x10)
        rc = handle_std(adu, len, pdu, plen);
    else if (fc == 0x2B)
        rc = handle_devid(fd, adu, pdu, plen);
    else if (fc == 0x41 || fc == 0x42)
        rc = handle_mfg(fd, adu, pdu, plen);
    else if (fc & 0x80) {
        /* modbus_reply_exception() would add 0x80 again and truncate it;
           answer FC|0x80 (unchanged) with exception 01 as a raw reply */
        uint8_t e[2] = {(uint8_t)fc, EX_FUNC};
        diag.exceptions++;
        rc = send_raw(fd, adu, e, 2);
    }
    else
        rc = reply_exc(adu, EX_FUNC);
    return rc < 0 ? -1 : 0;
}

/* ------------------------------------------------------------------ */
/* State dump                                                          */
static void json_str(FILE *f, const char *s)
{
    fputc('"', f);
    for (; *s; s++) {
        unsigned char c = (unsigned char)*s;
        if (c == '"' || c == '\\') fprintf(f, "\\%c", c);
        else if (c < 0x20) fprintf(f, "\\u%04x", c);
        else fputc(c, f);
    }
    fputc('"', f);
}

static void dump_vend(FILE *f, const vend_t *v)
{
    fprintf(f, "{\"AO\": %d, ", v->ao);
    for (int p = 0; p < 4; p++)
        fprintf(f, "\"S%d\": {\"type\": %d, \"active\": %d, \"sink_source\": %d}, ", p + 1, v->pt_type[p],
                v->pt_act[p], v->pt_sink[p]);
    fprintf(f, "\"S5\": {\"mode\": %d, \"range\": %d}, ", v->an_mode, v->an_range);
    fprintf(f, "\"MU_lead_lag\": %d, \"RD\": %d, \"AJ\": %d, \"AT\": %d, \"BE\": %d, \"BL\": %lld, \"BM\": %d, ",
            v->mu_b, v->rd, v->aj, v->at, v->be, (long long)v->bl, v->bm);
    fprintf(f, "\"DJ\": %d, \"DT\": %d, \"FS\": %lld, \"FL\": %d, ", v->dj, v->dt, (long long)v->fs, v->fl);
    fprintf(f, "\"LS\": {\"direction\": %d, \"position\": %lld, \"enable\": %d}, ", v->ls_dir,
            (long long)v->ls_pos, v->ls_en);
    fprintf(f, "\"TR\": [%lld, %lld, %lld]}", (long long)v->tr[0], (long long)v->tr[1], (long long)v->tr[2]);
}

static void write_state(void)
{
    if (!state_file) return;
    update_motion();
    char tmp[4096];
    snprintf(tmp, sizeof(tmp), "%s.tmp", state_file);
    FILE *f = fopen(tmp, "w");
    if (!f) return;
    fprintf(f, "{\n  \"device\": \"LMDCE572 (Lexium MDrive Ethernet, closed loop)\",\n");
    fprintf(f, "  \"word_order\": \"low word first\",\n  \"holding_registers\": {\n");
    int first = 1;
    for (int i = 0; i < NITEMS; i++) {
        fprintf(f, "%s    \"0x%04X\": {\"mcode\": ", first ? "" : ",\n", items[i].addr);
        json_str(f, items[i].mn);
        fprintf(f, ", \"registers\": %d, ", items[i].nregs);
        if (items[i].acc == ACC_WO)
            fprintf(f, "\"access\": \"WO\", \"value\": null}");
        else
            fprintf(f, "\"access\": \"%s\", \"value\": %lld}",
                    items[i].acc == ACC_RO ? "RO" : "RW", (long long)get_item(i));
        first = 0;
    }
    fprintf(f, "\n  },\n  \"coils\": {");
    for (int k = 0; k < 4; k++) fprintf(f, "%s\"%d\": %d", k ? ", " : "", k, point_level(k));
    fprintf(f, "},\n  \"discrete_inputs\": {");
    for (int k = 0; k < 4; k++) fprintf(f, "%s\"%d\": %d", k ? ", " : "", k, point_level(k));
    fprintf(f, "},\n  \"output_latches\": [%d, %d, %d, %d],\n", out_latch[0], out_latch[1], out_latch[2],
            out_latch[3]);
    fprintf(f, "  \"mfg_settings\": ");
    dump_vend(f, &vend);
    fprintf(f, ",\n  \"mfg_readonly\": {\"IT\": \"38,41\", \"VT\": \"24,48\", \"EL\": \"1000\"},\n");
    fprintf(f, "  \"program\": {\"loaded\": %s, \"running\": false, \"upgrade_mode\": %s},\n",
            program_loaded ? "true" : "false", upgrade_mode ? "true" : "false");
    fprintf(f, "  \"nvm\": {\"registers\": {");
    first = 1;
    for (int i = 0; i < NITEMS; i++) {
        if (items[i].kind != K_PARAM) continue;
        fprintf(f, "%s\"0x%04X\": %lld", first ? "" : ", ", items[i].addr, (long long)nvm_val[i]);
        first = 0;
    }
    fprintf(f, "}, \"mfg_settings\": ");
    dump_vend(f, &nvm_vend);
    fprintf(f, "},\n  \"device_identification\": {");
    for (int id = 0; id <= 6; id++) {
        fprintf(f, "%s\"%d\": ", id ? ", " : "", id);
        json_str(f, devid_obj(id));
    }
    fprintf(f, "},\n  \"diagnostic_counters\": {\"frames\": %lu, \"exceptions\": %lu, \"dropped\": %lu, "
               "\"connections\": %lu, \"bad_framing\": %lu}\n}\n",
            diag.frames, diag.exceptions, diag.dropped, diag.connections, diag.bad_framing);
    fclose(f);
    rename(tmp, state_file);
}

/* ------------------------------------------------------------------ */
#define MAXCL 32
typedef struct { int fd; int len; uint8_t buf[1024]; } client_t;
static client_t cl[MAXCL];

static void close_client(int k)
{
    close(cl[k].fd);
    cl[k].fd = -1;
    cl[k].len = 0;
}

/* returns -1 to close */
static int client_input(int k)
{
    client_t *c = &cl[k];
    ssize_t n = recv(c->fd, c->buf + c->len, sizeof(c->buf) - c->len, 0);
    if (n <= 0) {
        if (n < 0 && (errno == EINTR || errno == EAGAIN)) return 0;
        return -1;
    }
    c->len += (int)n;
    while (c->len >= 6) {
        int proto = (c->buf[2] << 8) | c->buf[3];
        int l = (c->buf[4] << 8) | c->buf[5];
        if (l > 254) { diag.bad_framing++; return -1; } /* cannot resynchronise */
        if (c->len < 6 + l) break;
        int total = 6 + l;
        if (proto != 0 || l < 2) {
            diag.dropped++; /* not a MODBUS ADU: discard silently */
        } else {
            if (process_adu(c->fd, c->buf, total) < 0) return -1;
        }
        memmove(c->buf, c->buf + total, c->len - total);
        c->len -= total;
    }
    return 0;
}

int main(int argc, char **argv)
{
    const char *listen_arg = NULL;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--listen") && i + 1 < argc) listen_arg = argv[++i];
        else if (!strcmp(argv[i], "--state") && i + 1 < argc) state_file = argv[++i];
        else { fprintf(stderr, "usage: %s --listen IP:PORT [--state FILE]\n", argv[0]); return 2; }
    }
    if (!listen_arg) { fprintf(stderr, "usage: %s --listen IP:PORT [--state FILE]\n", argv[0]); return 2; }
    char ip[64];
    const char *colon = strrchr(listen_arg, ':');
    if (!colon || colon - listen_arg >= (int)sizeof(ip)) { fprintf(stderr, "bad --listen\n"); return 2; }
    memcpy(ip, listen_arg, colon - listen_arg);
    ip[colon - listen_arg] = 0;
    int port = atoi(colon + 1);

    init_state();

    struct sigaction sa;
    memset(&sa, 0, sizeof(sa));
    sa.sa_handler = on_term;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sa.sa_handler = on_usr1;
    sigaction(SIGUSR1, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    ctx = modbus_new_tcp(ip, port);
    if (!ctx) { perror("modbus_new_tcp"); return 1; }
    /* exceptions raised by modbus_reply itself would otherwise sleep this long and flush */
    modbus_set_response_timeout(ctx, 0, 1000);
    map = modbus_mapping_new(4, 4, NREG, 0);
    if (!map) { perror("modbus_mapping_new"); return 1; }
    int ls = modbus_tcp_listen(ctx, 8);
    if (ls < 0) { fprintf(stderr, "listen: %s\n", modbus_strerror(errno)); return 1; }
    struct sockaddr_in sin;
    socklen_t sl = sizeof(sin);
    getsockname(ls, (struct sockaddr *)&sin, &sl);
    for (int k = 0; k < MAXCL; k++) cl[k].fd = -1;
    last_tick = now_s();
    mo.calib_end = 0.0;

    printf("listening tcp %s:%d\n", ip, ntohs(sin.sin_port));
    fflush(stdout);

    while (!g_quit) {
        if (g_dump) { g_dump = 0; write_state(); }
        fd_set rs;
        FD_ZERO(&rs);
        FD_SET(ls, &rs);
        int mx = ls;
        for (int k = 0; k < MAXCL; k++)
            if (cl[k].fd >= 0) { FD_SET(cl[k].fd, &rs); if (cl[k].fd > mx) mx = cl[k].fd; }
        struct timeval tv = {0, 10000};
        int r = select(mx + 1, &rs, NULL, NULL, &tv);
        update_motion();
        if (r < 0) continue;
        if (FD_ISSET(ls, &rs)) {
            int s = ls;
            int fd = modbus_tcp_accept(ctx, &s);
            if (fd >= 0) {
                int k;
                for (k = 0; k < MAXCL && cl[k].fd >= 0; k++) {}
                if (k == MAXCL || fd >= FD_SETSIZE) {
                    close(fd);
                } else {
                    int one = 1;
                    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
                    cl[k].fd = fd; cl[k].len = 0;
                    diag.connections++;
                }
            }
        }
        for (int k = 0; k < MAXCL; k++) {
            if (cl[k].fd >= 0 && FD_ISSET(cl[k].fd, &rs)) {
                if (client_input(k) < 0) close_client(k);
            }
        }
    }
    write_state();
    for (int k = 0; k < MAXCL; k++) if (cl[k].fd >= 0) close_client(k);
    close(ls);
    modbus_mapping_free(map);
    modbus_free(ctx);
    return 0;
}

#!/usr/bin/env node
"use strict";
/*
 * MDrive Plus2 / MDrive Hybrid Motion Control, Ethernet (MODBUS/TCP) simulator.
 * Built on modbus-serial 8.0.25 (ServerTCP).  See DECISIONS.md for every
 * place where the manual is wrong/silent or where we wrap the library.
 *
 * Layering:
 *   TCP socket -> our MBAP framer + request pre-check (this file)
 *              -> shim socket -> modbus-serial ServerTCP connection handler
 *              -> vector callbacks (this file) -> device model (this file)
 * Vendor function codes 0x41/0x42, unsupported function codes and malformed
 * PDUs are answered by the framer and never reach the library.
 */
const fs = require("fs");
const path = require("path");
const EventEmitter = require("events");
const ModbusRTU = require("modbus-serial");
const ServerTCP = ModbusRTU.ServerTCP;

/* ------------------------------------------------------------------ CLI */
function parseArgs(argv) {
    const o = { listen: null, state: null, model: "hybrid" };
    for (let i = 0; i < argv.length; i++) {
        const a = argv[i];
        if (a === "--listen") o.listen = argv[++i];
        else if (a === "--state") o.state = argv[++i];
        else if (a === "--model") o.model = argv[++i];
        else {
            process.stderr.write("unknown argument " + a + "\n");
            process.exit(2);
        }
    }
    if (!o.listen) {
        process.stderr.write("usage: node sim.js --listen 127.0.0.1:PORT [--state FILE] [--model hybrid|plus]\n");
        process.exit(2);
    }
    if (o.model !== "hybrid" && o.model !== "plus") {
        process.stderr.write("--model must be hybrid or plus\n");
        process.exit(2);
    }
    const m = /^(.*):(\d+)$/.exec(o.listen);
    if (!m) { process.stderr.write("bad --listen\n"); process.exit(2); }
    o.host = m[1];
    o.port = parseInt(m[2], 10);
    if (o.host !== "127.0.0.1") {
        process.stderr.write("this simulator only binds to 127.0.0.1\n");
        process.exit(2);
    }
    return o;
}
const opts = parseArgs(process.argv.slice(2));
const MODEL = opts.model;            // "hybrid" (default) or "plus"

/* ------------------------------------------------------- Modbus errors */
function mbErr(code, msg) {
    const e = new Error(msg || ("modbus exception " + code));
    e.modbusErrorCode = code;      // the field modbus-serial's callback reads
    return e;
}
const ILLEGAL_FUNCTION = 1, ILLEGAL_ADDRESS = 2, ILLEGAL_VALUE = 3, DEVICE_FAILURE = 4;

/* ------------------------------------------------------- device state */
const INT32_MIN = -2147483648, INT32_MAX = 2147483647;
const wrap32 = (v) => { v = Math.round(v); return ((v % 4294967296) + 4294967296) % 4294967296 | 0; };

const MS_ALLOWED = [1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127];

const dev = {
    p: {},                         // parameter values by mnemonic
    io: {                          // I/O 1-4 setup (S1..S4): [type, active, sink]
        1: [0, 0, 0], 2: [0, 0, 0], 3: [0, 0, 0], 4: [0, 0, 0]
    },
    outLatch: { 1: 0, 2: 0, 3: 0, 4: 0 },   // general purpose output latches
    clockIo: { 7: [33, 0], 8: [33, 0] },    // S7/S8
    analogSetup: [9, 0],                    // S5
    captureTrip: [60, 0],                   // S13
    clockRatio: 1.0,                        // CR
    tripRel: 0,                             // TR
    makeUpParam: 0,                         // MU second parameter (B)
    program: { state: "stopped", label: "" },
    // motion (not dumped except through the registers it drives)
    mot: { mode: "idle", target: 0, v: 0, slewV: 0, pos: 0 },
    calibrating: false,
    tripRef: 0,
};

/* register table -------------------------------------------------------
 * addr, words, mnemonic, access, min, max, default, model, signed      */
const REGS = [];
function R(addr, words, mn, access, min, max, def, model, extra) {
    REGS.push(Object.assign({ addr, words, mn, access, min, max, def, model: model || "all" }, extra || {}));
}
// base map (manual section 5)
R(0x0000, 2, "A", "rw", 91, 1525878997, 1000000);
R(0x0005, 2, "C1", "rw", INT32_MIN, INT32_MAX, 0);
R(0x0007, 2, "C2", "rw", INT32_MIN, INT32_MAX, 0);
R(0x0009, 1, "CE", "rw", 0, 1, 1);
R(0x000B, 1, "CM", "rw", 0, 1, 0, "plus");
R(0x000F, 1, "D1", "rw", 0, 255, 0);
R(0x0010, 1, "D2", "rw", 0, 255, 0);
R(0x0011, 1, "D3", "rw", 0, 255, 0);
R(0x0012, 1, "D4", "rw", 0, 255, 0);
R(0x0013, 1, "D5", "rw", 0, 255, 0);
R(0x0018, 2, "D", "rw", 91, 1525878997, 1000000);
R(0x001A, 1, "DB", "rw", 0, 65000, 10, "plus");
R(0x001B, 1, "DC", "wo", 1, 12, null);
R(0x001C, 1, "DE", "rw", 0, 1, 1);
R(0x001E, 1, "EE", "rw", 0, 1, 0);
R(0x001F, 1, "EF", "ro", 0, 1, 0);
R(0x0021, 1, "ER", "rw", 0, 0, 0);           // write: only 0 (clear)
R(0x0029, 1, "HC", "rw", 0, 100, 5);
R(0x002B, 1, "HM", "rw", 1, 4, 1);
R(0x002C, 1, "HT", "rw", 0, 65535, 500);
R(0x002D, 1, "I1", "ro", 0, 1, null);
R(0x002E, 1, "I2", "ro", 0, 1, null);
R(0x002F, 1, "I3", "ro", 0, 1, null);
R(0x0030, 1, "I4", "ro", 0, 1, null);
R(0x0031, 1, "I5", "ro", 0, 1023, null);
R(0x0032, 1, "I6", "ro", 0, 1, null, "plus");
R(0x0037, 1, "IC", "wo", 1, 12, null);
R(0x003A, 1, "IL", "ro", 0, 15, null);
R(0x003B, 1, "IN", "ro", 0, 15, null);
R(0x003F, 1, "JE", "rw", 0, 1, 0);
R(0x0042, 1, "LM", "rw", 1, 6, 1);
R(0x0043, 2, "MA", "wo", INT32_MIN, INT32_MAX, null);
R(0x0045, 1, "MP", "ro", 0, 1, 0);
R(0x0046, 2, "MR", "wo", INT32_MIN, INT32_MAX, null);
R(0x0048, 1, "MS", "rw", 1, 256, 256);
R(0x0049, 1, "MT", "rw", 0, 65000, 0);
R(0x004A, 1, "MV", "ro", 0, 1, 0);
R(0x004B, 1, "O1", "rw", 0, 1, null);
R(0x004C, 1, "O2", "rw", 0, 1, null);
R(0x004D, 1, "O3", "rw", 0, 1, null);
R(0x004E, 1, "O4", "rw", 0, 1, null);
R(0x0055, 1, "OL", "rw", 0, 15, null);
R(0x0056, 1, "OT", "rw", 0, 15, null);
R(0x0057, 2, "P", "rw", INT32_MIN, INT32_MAX, 0);
R(0x0059, 2, "PC", "ro", INT32_MIN, INT32_MAX, 0);
R(0x005C, 1, "PM", "rw", 0, 1, 0, "plus");
R(0x005F, 2, "R1", "rw", INT32_MIN, INT32_MAX, 0);
R(0x0061, 2, "R2", "rw", INT32_MIN, INT32_MAX, 0);
R(0x0063, 2, "R3", "rw", INT32_MIN, INT32_MAX, 0);
R(0x0065, 2, "R4", "rw", INT32_MIN, INT32_MAX, 0);
R(0x0067, 1, "RC", "rw", 1, 100, 25);
R(0x0076, 1, "S", "wo", 0, 65535, null);
R(0x0077, 1, "SF", "rw", 0, 65000, 15, "plus");
R(0x0078, 2, "SL", "wo", -5000000, 5000000, null);
R(0x007A, 1, "SM", "rw", 0, 1, 0, "plus");
R(0x007B, 1, "ST", "rw", 0, 0, 0, "plus");    // write: only 0 (clear)
R(0x007D, 1, "TE", "rw", 0, 63, 0);
R(0x0085, 2, "V", "ro", INT32_MIN, INT32_MAX, 0);
R(0x0088, 1, "VC", "ro", 0, 1, 0);
R(0x0089, 2, "VI", "rw", 1, 4999999, 1000);
R(0x008B, 2, "VM", "rw", 2, 5000000, 768000);
// hybrid specific (section 5.1)
R(0x008E, 1, "AS", "rw", 0, 3, 2, "hybrid");
R(0x008F, 1, "AF", "ro", 0, 255, null, "hybrid");
R(0x0090, 1, "CA", "rw", 0, 1, 1, "hybrid");
R(0x0091, 1, "CB", "rw", 0, 3, 1, "hybrid");
R(0x0092, 1, "CC", "rw", 1, 100, 100, "hybrid");
R(0x0093, 1, "CF", "wo", 0, 65535, null, "hybrid");
R(0x0094, 1, "CT", "rw", 2, 65535, 200, "hybrid");
R(0x0095, 2, "LD", "rw", 0, INT32_MAX, 102400, "hybrid");
R(0x0097, 2, "LG", "rw", 0, INT32_MAX, 102400, "hybrid");
R(0x0099, 2, "LL", "ro", -INT32_MAX, INT32_MAX, 0, "hybrid");
R(0x009B, 1, "LR", "ro", 0, 1, 0, "hybrid");
R(0x009C, 2, "LT", "rw", 2, 65535, 2000, "hybrid");
R(0x009E, 2, "MF", "rw", 306, 5000000, 768000, "hybrid");
R(0x00A0, 1, "MU", "rw", 0, 2, 0, "hybrid");
R(0x00A1, 1, "SC", "wo", 0, 65535, null, "hybrid");
R(0x00A2, 1, "SS", "rw", 0, 255, 0, "hybrid");
R(0x00A5, 1, "TD", "rw", 0, 1, 1, "hybrid");
R(0x00A6, 1, "TQ", "rw", 1, 100, 25, "hybrid");
R(0x00A7, 1, "TS", "rw", 0, 255, 0, "hybrid");
// user variables (section 5.2)
for (let i = 0; i < 8; i++) R(0x00A8 + 2 * i, 2, "V" + (i + 1), "rw", INT32_MIN, INT32_MAX, 0);

const ACTIVE = REGS.filter((r) => r.model === "all" || r.model === MODEL);
const BY_WORD = new Map();      // 16-bit address -> {reg, idx}
for (const r of ACTIVE) for (let k = 0; k < r.words; k++) BY_WORD.set(r.addr + k, { reg: r, idx: k });
const BY_MN = new Map(ACTIVE.map((r) => [r.mn, r]));
for (const r of ACTIVE) if (r.def !== null && r.access !== "wo") dev.p[r.mn] = r.def;

/* ---------------------------------------------------------- I/O model */
const INPUT_TYPES = [0, 1, 2, 3, 5, 7, 8, 11];
const OUTPUT_TYPES = MODEL === "hybrid" ? [16, 17, 18, 20, 21, 23, 24, 25] : [16, 17, 18, 20, 21, 23];
const isOutput = (n) => dev.io[n][0] >= 16;
function outputState(n) {
    switch (dev.io[n][0]) {
        case 16: return dev.outLatch[n];
        case 17: return dev.mot.mode !== "idle" ? 1 : 0;
        case 18: return dev.p.EF ? 1 : 0;
        case 20: return velocityChanging() ? 1 : 0;
        case 21: return dev.p.LR ? 1 : 0;
        case 23: return dev.mot.mode === "pos" ? 1 : 0;
        case 24: return dev.p.AS ? 1 : 0;
        case 25: return 0;   // no make-up in progress: no load, no missed steps
        default: return 0;   // configured as input: output latch off
    }
}
// logic state of a point read as an input: nothing is wired to the
// simulated inputs, so they are inactive; outputs read back their level.
const inputState = (n) => (isOutput(n) ? outputState(n) : 0);
const inputsBCD = () => inputState(1) | inputState(2) << 1 | inputState(3) << 2 | inputState(4) << 3;
const outputsBCD = () => outputState(1) | outputState(2) << 1 | outputState(3) << 2 | outputState(4) << 3;

/* ---------------------------------------------------------- motion model */
const TICK_MS = 10;
let motionTimer = null;
function velocityChanging() {
    const m = dev.mot;
    if (m.mode === "idle") return false;
    if (m.mode === "slew") return Math.abs(m.v - m.slewV) > 0.5;
    return Math.abs(Math.abs(m.v) - dev.p.VM) > 0.5;
}
function startMotion() {
    if (!motionTimer) motionTimer = setInterval(motionTick, TICK_MS);
}
function stopMotion() {
    dev.mot.mode = "idle"; dev.mot.v = 0; dev.mot.slewV = 0;
    if (motionTimer) { clearInterval(motionTimer); motionTimer = null; }
}
function advance(deltaSteps) {
    const m = dev.mot;
    const before = Math.round(m.pos);
    m.pos += deltaSteps;
    const moved = Math.round(m.pos) - before;
    if (moved !== 0) {
        dev.p.P = wrap32(dev.p.P + moved);
        dev.p.C1 = wrap32(dev.p.C1 + moved);
        if (dev.p.EE) dev.p.C2 = wrap32(dev.p.C2 + moved);
        // trip on relative position (TE bit 16 with TR distance)
        if ((dev.p.TE & 16) && dev.tripRel !== 0 && Math.abs(dev.p.P - dev.tripRef) >= Math.abs(dev.tripRel)) {
            dev.p.TE &= ~16;    // one-shot: re-enable through 0x007D
        }
    }
}
function motionTick() {
    const m = dev.mot, dt = TICK_MS / 1000, p = dev.p;
    if (m.mode === "slew") {
        const tv = m.slewV;
        if (m.v < tv) m.v = Math.min(tv, m.v + (m.v >= 0 ? p.A : p.D) * dt);
        else if (m.v > tv) m.v = Math.max(tv, m.v - (m.v <= 0 ? p.A : p.D) * dt);
        advance(m.v * dt);
        if (tv === 0 && m.v === 0) stopMotion();
        return;
    }
    if (m.mode === "pos") {
        const rem = m.target - m.pos;
        const dir = Math.sign(rem);
        let speed = Math.abs(m.v);
        const stopDist = (speed * speed) / (2 * p.D);
        if (Math.abs(rem) <= stopDist + speed * dt) speed = Math.max(p.VI, speed - p.D * dt);
        else speed = Math.min(p.VM, Math.max(p.VI, speed + p.A * dt));
        const step = speed * dt;
        if (Math.abs(rem) <= step || dir === 0) {
            advance(rem);
            m.pos = Math.round(m.pos);
            stopMotion();
            return;
        }
        m.v = dir * speed;
        advance(m.v * dt);
        return;
    }
    stopMotion();
}
function beginMove(targetAbs) {
    const m = dev.mot;
    m.pos = dev.p.P;
    m.target = targetAbs;
    m.v = 0;
    m.mode = "pos";
    startMotion();
}

/* ------------------------------------------------ hybrid calibration */
let calTimer = null;
function startCalibration() {
    if (MODEL !== "hybrid") return;
    dev.calibrating = true;
    if (calTimer) clearTimeout(calTimer);
    calTimer = setTimeout(() => { dev.calibrating = false; calTimer = null; }, dev.p.CT || 200);
    calTimer.unref();
}
function hybridStatus() {
    let af = 0;
    if (dev.p.LR) af |= 8;
    if (dev.p.AS) af |= 16;
    if ((dev.p.LL | 0) === 0) af |= 64;
    if (!dev.calibrating) af |= 128;
    return af;
}

/* ------------------------------------------------ register read/write */
function readValue(reg) {
    switch (reg.mn) {
        case "I1": return inputState(1);
        case "I2": return inputState(2);
        case "I3": return inputState(3);
        case "I4": return inputState(4);
        case "I5": return 0;                  // analog input: nothing connected
        case "I6": return 0;                  // index mark not under the shaft
        case "IL": case "IN": return inputsBCD();
        case "O1": return outputState(1);
        case "O2": return outputState(2);
        case "O3": return outputState(3);
        case "O4": return outputState(4);
        case "OL": case "OT": return outputsBCD();
        case "MV": return dev.mot.mode !== "idle" ? 1 : 0;
        case "MP": return dev.mot.mode === "pos" ? 1 : 0;
        case "VC": return velocityChanging() ? 1 : 0;
        case "V": return dev.p.AS === 3 ? 0 : Math.round(dev.mot.v);
        case "AF": return hybridStatus();
        default: return dev.p[reg.mn];
    }
}
function toWords(reg, value) {
    if (reg.words === 1) return [value & 0xFFFF];
    const u = value >>> 0;                    // high word first (manual 4.2.4)
    return [(u >>> 16) & 0xFFFF, u & 0xFFFF];
}

// Collect the parameters an address block covers. 02 for holes, model
// absent registers, wrong direction, and (writes) partial 32-bit params.
function coverage(start, qty, write) {
    const list = [];
    for (let a = start; a < start + qty; a++) {
        const hit = BY_WORD.get(a);
        if (!hit) throw mbErr(ILLEGAL_ADDRESS, "reserved/unmapped " + a);
        const r = hit.reg;
        if (write && r.access === "ro") throw mbErr(ILLEGAL_ADDRESS, "read-only " + r.mn);
        if (!write && r.access === "wo") throw mbErr(ILLEGAL_ADDRESS, "write-only " + r.mn);
        if (write && (hit.idx !== 0 && a === start)) throw mbErr(ILLEGAL_ADDRESS, "partial write");
        if (hit.idx === 0) list.push({ reg: r, off: a - start });
        if (write && hit.idx === 0 && a + r.words > start + qty) throw mbErr(ILLEGAL_ADDRESS, "partial write");
    }
    return list;
}

function readBlock(start, qty) {
    if (start + qty > 0x10000) throw mbErr(ILLEGAL_ADDRESS);
    coverage(start, qty, false);
    const out = [];
    const readClears = [];
    for (let a = start; a < start + qty; a++) {
        const { reg, idx } = BY_WORD.get(a);
        const words = toWords(reg, readValue(reg));
        out.push(words[idx]);
        if (reg.mn === "ER") readClears.push(reg);
    }
    // ER: "must be read or set to 0 to clear" (manual line 1047)
    if (readClears.length && dev.p.ER !== 0) { dev.p.ER = 0; dev.p.EF = 0; }
    return out;
}

function decode(reg, words) {
    if (reg.words === 1) return words[0];
    const u = (words[0] << 16 | words[1]) >>> 0;
    return reg.min < 0 ? (u | 0) : u;
}

function writeBlock(start, values) {
    const qty = values.length;
    if (start + qty > 0x10000) throw mbErr(ILLEGAL_ADDRESS);
    const items = coverage(start, qty, true);
    // decode + range check everything first (atomic request)
    const newVals = {};
    for (const it of items) {
        const v = decode(it.reg, values.slice(it.off, it.off + it.reg.words));
        it.value = v;
        if (it.reg.mn === "MS") {
            if (!MS_ALLOWED.includes(v)) throw mbErr(ILLEGAL_VALUE, "MS");
        } else if (v < it.reg.min || v > it.reg.max) {
            throw mbErr(ILLEGAL_VALUE, it.reg.mn + " out of range");
        }
        newVals[it.reg.mn] = v;
    }
    // cross-parameter rules with the values this request would leave
    const get = (mn) => (mn in newVals ? newVals[mn] : dev.p[mn]);
    if ("VI" in newVals || "VM" in newVals) {
        if (!(get("VI") < get("VM"))) throw mbErr(ILLEGAL_VALUE, "VI must be < VM");
    }
    if ("HT" in newVals) {
        if (get("HT") === 1) throw mbErr(ILLEGAL_VALUE, "HT 0 or 2..65535");
    }
    if ("HT" in newVals || "MT" in newVals) {
        if (get("HT") + get("MT") > 65535) throw mbErr(ILLEGAL_VALUE, "HT+MT > 65535");
    }
    // execution-time checks (device cannot do it now) -> 04
    const moving = dev.mot.mode !== "idle";
    for (const it of items) {
        const mn = it.reg.mn;
        if ((mn === "MA" || mn === "MR") && (moving || !get("DE"))) throw mbErr(DEVICE_FAILURE, "busy/disabled");
        if (mn === "SL" && it.value !== 0 && (dev.mot.mode === "pos" || !get("DE"))) throw mbErr(DEVICE_FAILURE, "busy/disabled");
        if ((mn === "P" || mn === "MS") && moving) throw mbErr(DEVICE_FAILURE, "moving");
        if (/^O[1-4]$/.test(mn)) {
            const n = +mn[1];
            if (dev.io[n][0] !== 16) throw mbErr(DEVICE_FAILURE, "I/O " + n + " not a general purpose output");
        }
        if ((mn === "DC" || mn === "IC")) { /* selector already range-checked */ }
    }
    // apply
    for (const it of items) applyWrite(it.reg, it.value);
}

function varSelector(sel) {
    return sel <= 4 ? "R" + sel : "V" + (sel - 4);
}
function applyWrite(reg, v) {
    const p = dev.p;
    switch (reg.mn) {
        case "MA": beginMove(v); return;
        case "MR": beginMove(p.P + v); return;
        case "SL":
            if (v === 0) { if (dev.mot.mode === "slew") dev.mot.slewV = 0; return; }
            if (dev.mot.mode !== "slew") { dev.mot.mode = "slew"; dev.mot.v = 0; dev.mot.pos = p.P; }
            dev.mot.slewV = v;
            startMotion();
            return;
        case "DE":
            if (!v && dev.mot.mode !== "idle") stopMotion();       // bridge off: motion aborted
            if (v && !p.DE) startCalibration();                     // bridge re-enabled
            p.DE = v; return;
        case "ER": p.ER = 0; p.EF = 0; return;
        case "ST": p.ST = 0; return;
        case "DC": { const k = varSelector(v); p[k] = wrap32(p[k] - 1); return; }
        case "IC": { const k = varSelector(v); p[k] = wrap32(p[k] + 1); return; }
        case "O1": case "O2": case "O3": case "O4": dev.outLatch[+reg.mn[1]] = v; return;
        case "OL": case "OT":
            for (let n = 1; n <= 4; n++) if (dev.io[n][0] === 16) dev.outLatch[n] = (v >> (n - 1)) & 1;
            return;
        case "S": return;                       // save to NVM: nothing observable
        case "TE":
            if ((v & 16) && !(p.TE & 16)) dev.tripRef = p.P;
            p.TE = v; return;
        case "MS": if (v !== p.MS) { p.MS = v; startCalibration(); } return;
        case "AS": if (v && !p.AS) startCalibration(); p.AS = v; return;
        case "CF": p.LR = 0; startCalibration(); return;
        case "SC": startCalibration(); return;
        case "P": p.P = v; dev.mot.pos = v; return;
        default: p[reg.mn] = v;
    }
}

/* ------------------------------------------- manufacturer functions */
const isDigits = (s) => /^[0-9]+$/.test(s);
function parseList(data, n) {
    // "=A,B[,C]" exactly, decimal digits, no spaces
    if (data[0] !== "=") return null;
    const parts = data.slice(1).split(",");
    if (parts.length !== n || !parts.every((x) => isDigits(x) && x.length <= 2)) return null;
    return parts.map(Number);
}
const MFG = {
    S1: ioSetup(1), S2: ioSetup(2), S3: ioSetup(3), S4: ioSetup(4),
    S7: clockSetup(7), S8: clockSetup(8),
    CR: {
        read: () => dev.clockRatio.toFixed(3),
        write: (d) => {
            if (d.length > 6 || !/^=-?(\d+(\.\d*)?|\.\d+)$/.test(d)) throw mbErr(ILLEGAL_VALUE);
            const v = parseFloat(d.slice(1));
            if (!isFinite(v) || v === 0) throw mbErr(ILLEGAL_VALUE);
            return () => { dev.clockRatio = v; };
        },
    },
    S5: {
        read: () => dev.analogSetup.join(", "),
        write: (d) => {
            const v = d.length >= 4 && d.length <= 5 ? parseList(d, 2) : null;
            if (!v || ![9, 10].includes(v[0]) || v[1] > 1) throw mbErr(ILLEGAL_VALUE);
            return () => { dev.analogSetup = v; };
        },
    },
    S13: {
        read: () => dev.captureTrip.join(", "),
        write: (d) => {
            const v = d.length >= 4 && d.length <= 5 ? parseList(d, 2) : null;
            if (!v || ![60, 61].includes(v[0]) || v[1] > 1) throw mbErr(ILLEGAL_VALUE);
            return () => { dev.captureTrip = v; };
        },
    },
    TR: {
        read: () => String(dev.tripRel),
        write: (d) => {
            if (d.length > 11 || !/^=[+-]?\d+$/.test(d)) throw mbErr(ILLEGAL_VALUE);
            const v = parseInt(d.slice(1), 10);
            if (v < INT32_MIN || v > INT32_MAX) throw mbErr(ILLEGAL_VALUE);
            return () => { dev.tripRel = v; };
        },
    },
    E: { cmd: true, run: () => { dev.program = { state: "stopped", label: "" }; } },
    PS: { cmd: true, run: () => { if (dev.program.state === "running") dev.program.state = "paused"; } },
    RS: { cmd: true, run: () => { if (dev.program.state === "paused") dev.program.state = "running"; } },
    EX: {
        cmd: true, needsArg: true,
        run: (label) => {
            if (!/^([A-Za-z][A-Za-z0-9]|[0-9]{1,4})$/.test(label)) throw mbErr(ILLEGAL_VALUE, "label");
            if (dev.program.state !== "stopped") throw mbErr(DEVICE_FAILURE, "program already running");
            dev.program = { state: "running", label };
        },
    },
};
if (MODEL === "hybrid") {
    MFG.MU = {
        read: () => dev.p.MU + ", " + dev.makeUpParam,
        write: (d) => {
            const v = d.length === 4 ? parseList(d, 2) : null;
            if (!v || v[0] > 2 || v[1] > 1) throw mbErr(ILLEGAL_VALUE);
            return () => { dev.p.MU = v[0]; dev.makeUpParam = v[1]; if (v[1] === 1) dev.p.LL = 0; };
        },
    };
}
function ioSetup(n) {
    return {
        read: () => dev.io[n].join(", "),
        write: (d) => {
            const v = d.length >= 6 && d.length <= 7 ? parseList(d, 3) : null;
            if (!v || !(INPUT_TYPES.includes(v[0]) || OUTPUT_TYPES.includes(v[0])) || v[1] > 1 || v[2] > 1) {
                throw mbErr(ILLEGAL_VALUE);
            }
            return () => {
                if (dev.io[n][0] !== v[0]) dev.outLatch[n] = 0;
                dev.io[n] = v;
            };
        },
    };
}
function clockSetup(n) {
    return {
        read: () => dev.clockIo[n].join(", "),
        write: (d) => {
            const v = d.length >= 4 && d.length <= 5 ? parseList(d, 2) : null;
            if (!v || ![33, 34, 35, 49, 50, 51].includes(v[0]) || v[1] > 1) throw mbErr(ILLEGAL_VALUE);
            return () => { dev.clockIo[n] = v; };
        },
    };
}
function decodeMnemonic(b) {
    // 4 bytes, ASCII of the mnemonic in reverse order, space padded
    const s = Buffer.from(b).reverse().toString("latin1");
    const m = /^([A-Z][A-Z0-9]{0,3}?) *$/.exec(s);
    return m ? m[1] : null;
}
// returns response PDU (Buffer) or throws mbErr
function handleMfg(pdu) {
    const fc = pdu[0];
    if (pdu.length < 5) throw mbErr(ILLEGAL_VALUE, "short");
    const mnBytes = pdu.subarray(1, 5);
    let data = null;
    if (fc === 0x42 || pdu.length > 5) {
        if (pdu.length < 6) throw mbErr(ILLEGAL_VALUE, "no byte count");
        const bc = pdu[5];
        if (pdu.length !== 6 + bc || bc > 28) throw mbErr(ILLEGAL_VALUE, "byte count");
        data = pdu.subarray(6).toString("latin1");
    }
    const mn = decodeMnemonic(mnBytes);
    const f = mn && MFG[mn];
    if (!f) throw mbErr(ILLEGAL_ADDRESS, "unknown mnemonic");
    if (f.cmd) {
        if (f.needsArg) {
            if (!data || data.length < 1 || data.length > 4) throw mbErr(ILLEGAL_VALUE);
            f.run(data);
        } else {
            if (data && data.length) throw mbErr(ILLEGAL_VALUE);
            f.run();
        }
    } else if (fc === 0x41) {
        if (data !== null) throw mbErr(ILLEGAL_VALUE, "read takes no data");
        const txt = Buffer.from(f.read(), "latin1");
        return Buffer.concat([Buffer.from([0x41, txt.length]), txt]);
    } else {
        if (!data || data.length < 1) throw mbErr(ILLEGAL_VALUE);
        const commit = f.write(data);
        commit();
    }
    if (fc === 0x41) return Buffer.from([0x41, 0x00]);
    return Buffer.concat([Buffer.from([0x42, 0x04]), Buffer.from(mnBytes)]);
}

/* --------------------------------------------- device identification */
const DEV_ID = {
    0x00: "SEM USA",
    0x01: MODEL === "hybrid" ? "MAI3CRL23C4-EQ" : "MDI3CRL23C4-EQ",
    0x02: "4.0.0.0",
    0x03: "www.imshome.com",
    0x04: "MDrive Ethernet",
    0x05: "069110437",
    0x06: "ASI 4.0.0.2",
};
let meiContext = null;   // read device id code of the FC43 request being processed

/* ---------------------------------------------------- library vector */
const vector = {
    getCoil(addr) {
        if (addr < 0x4B || addr > 0x4E) throw mbErr(ILLEGAL_ADDRESS);
        return outputState(addr - 0x4A) === 1;
    },
    getDiscreteInput(addr) {
        if (addr < 0x2D || addr > 0x30) throw mbErr(ILLEGAL_ADDRESS);
        return inputState(addr - 0x2C) === 1;
    },
    setCoil(addr, on) {
        if (addr < 0x4B || addr > 0x4E) throw mbErr(ILLEGAL_ADDRESS);
        writeBlock(addr, [on ? 1 : 0]);
    },
    getHoldingRegister(addr) { return readBlock(addr, 1)[0]; },
    getMultipleHoldingRegisters(addr, qty) { return readBlock(addr, qty); },
    setRegisterArray(addr, values) { writeBlock(addr, values); },
    readDeviceIdentification() {
        const code = meiContext;
        const o = {};
        for (const k of Object.keys(DEV_ID)) {
            if (code === 1 && +k > 2) continue;     // basic category only
            o[k] = DEV_ID[k];
        }
        return o;
    },
};

/* ------------------------------------------------------ counters */
const counters = {
    frames_received: 0, responses_sent: 0, exception_responses: 0,
    frames_discarded: 0, connections_closed_bad_framing: 0,
};

/* --------------------------------------------- server + framing */
const SUPPORTED_BY_LIBRARY = new Set([0x01, 0x02, 0x03, 0x05, 0x10, 0x2B]);

const server = new ServerTCP(vector, {
    host: opts.host,
    port: String(opts.port),      // library does `options.port || 502`; "0" is truthy
    unitID: 255,                  // answer every unit id (library default)
    debug: false,
});
server.on("error", () => {});
server.on("socketError", () => {});
server.on("serverError", (e) => {
    process.stderr.write("server error: " + e.message + "\n");
    process.exit(1);
});

const libConnection = server._server.listeners("connection")[0];
server._server.removeListener("connection", libConnection);

class LibSockShim extends EventEmitter {
    constructor(sock) {
        super();
        this.sock = sock;
        this.remoteAddress = sock.remoteAddress;
        this.localPort = sock.localPort;
    }
    address() { return this.sock.address(); }
    destroy() { this.sock.destroy(); }
    write(buf) {
        // FC43: conformity level is a device property (0x82 regular,
        // stream + individual); the library derives it from the objects
        // returned for this particular request.
        if (buf.length >= 11 && buf[7] === 0x2B && buf[8] === 0x0E) buf[10] = 0x82;
        if (buf.length >= 8 && (buf[7] & 0x80)) counters.exception_responses++;
        counters.responses_sent++;
        if (!this.sock.destroyed && this.sock.writable) this.sock.write(buf);
    }
}

function exceptionAdu(tid, unit, fc, code) {
    const b = Buffer.alloc(9);
    b.writeUInt16BE(tid, 0); b.writeUInt16BE(0, 2); b.writeUInt16BE(3, 4);
    b[6] = unit; b[7] = (fc | 0x80) & 0xFF; b[8] = code;
    return b;
}
function pduAdu(tid, unit, pdu) {
    const b = Buffer.alloc(7 + pdu.length);
    b.writeUInt16BE(tid, 0); b.writeUInt16BE(0, 2); b.writeUInt16BE(pdu.length + 1, 4);
    b[6] = unit; pdu.copy(b, 7);
    return b;
}

// Pre-check a standard request; returns exception code or 0 to forward.
function precheck(pdu) {
    const fc = pdu[0];
    switch (fc) {
        case 0x01: case 0x02: case 0x03: {
            if (pdu.length !== 5) return ILLEGAL_VALUE;
            const qty = pdu.readUInt16BE(3);
            if (qty < 1 || qty > 4) return ILLEGAL_VALUE;    // manual: 1 to 4
            return 0;
        }
        case 0x05: {
            if (pdu.length !== 5) return ILLEGAL_VALUE;
            const v = pdu.readUInt16BE(3);
            if (v !== 0x0000 && v !== 0xFF00) return ILLEGAL_VALUE;
            return 0;
        }
        case 0x10: {
            if (pdu.length < 6) return ILLEGAL_VALUE;
            const qty = pdu.readUInt16BE(3), bc = pdu[5];
            if (qty < 1 || qty > 4 || bc !== qty * 2 || pdu.length !== 6 + bc) return ILLEGAL_VALUE;
            return 0;
        }
        case 0x2B: {
            if (pdu.length < 2) return ILLEGAL_VALUE;
            if (pdu[1] !== 0x0E) return ILLEGAL_FUNCTION;       // only MEI 14 is supported
            if (pdu.length !== 4) return ILLEGAL_VALUE;
            return 0;
        }
        default: return ILLEGAL_FUNCTION;
    }
}

server._server.on("connection", (sock) => {
    sock.setNoDelay(true);
    const shim = new LibSockShim(sock);
    libConnection.call(server._server, shim);
    let buf = Buffer.alloc(0);
    const reply = (b) => setTimeout(() => shim.write(b), 0);   // keep pipelined order

    sock.on("error", () => {});
    sock.on("close", () => shim.emit("close"));
    sock.on("data", (chunk) => {
        try {
            buf = buf.length ? Buffer.concat([buf, chunk]) : chunk;
            while (buf.length >= 7) {
                const tid = buf.readUInt16BE(0), pid = buf.readUInt16BE(2), len = buf.readUInt16BE(4);
                if (len === 0 || len > 254) {          // framing lost: no way to resync
                    counters.connections_closed_bad_framing++;
                    buf = Buffer.alloc(0);
                    sock.destroy();
                    return;
                }
                if (buf.length < 6 + len) break;
                const frame = buf.subarray(0, 6 + len);
                buf = buf.subarray(6 + len);
                counters.frames_received++;
                if (pid !== 0 || len < 2) { counters.frames_discarded++; continue; }
                const unit = frame[6];
                const pdu = Buffer.from(frame.subarray(7));
                const fc = pdu[0];
                if (fc === 0x41 || fc === 0x42) {
                    let out;
                    try { out = pduAdu(tid, unit, handleMfg(pdu)); } catch (e) {
                        out = exceptionAdu(tid, unit, fc, e.modbusErrorCode || DEVICE_FAILURE);
                    }
                    reply(out);
                    continue;
                }
                const ex = precheck(pdu);
                if (ex) { reply(exceptionAdu(tid, unit, fc, ex)); continue; }
                if (fc === 0x2B) {
                    const code = pdu[2];
                    setTimeout(() => { meiContext = code; }, 0);   // runs right before the library's parse timer
                }
                shim.emit("data", Buffer.from(frame));   // library: MBAP + unit + PDU
            }
        } catch (e) {
            process.stderr.write("framer error: " + (e && e.stack) + "\n");
            buf = Buffer.alloc(0);
        }
    });
});

/* ------------------------------------------------------- state dump */
function stateObject() {
    const hr = {};
    for (const r of ACTIVE) {
        if (r.access === "wo") continue;
        const v = readValue(r);
        hr["0x" + r.addr.toString(16).padStart(4, "0").toUpperCase()] = {
            mcode: r.mn, words: r.words, access: r.access, value: v,
            registers: toWords(r, v),
        };
    }
    const coils = {}, inputs = {};
    for (let n = 1; n <= 4; n++) {
        coils["0x" + (0x4A + n).toString(16).padStart(4, "0").toUpperCase()] = outputState(n);
        inputs["0x" + (0x2C + n).toString(16).padStart(4, "0").toUpperCase()] = inputState(n);
    }
    const mfg = {};
    for (const k of Object.keys(MFG)) if (!MFG[k].cmd) mfg[k] = MFG[k].read();
    return {
        device: { product: MODEL === "hybrid" ? "MDrive 23 Hybrid Motion Control (Ethernet)" : "MDrive 23 Plus2 Motion Control (Ethernet)",
            model: MODEL, unit_ids: "all (0-255)" },
        holding_registers: hr,
        coils,
        discrete_inputs: inputs,
        manufacturer_specific: mfg,
        program: Object.assign({}, dev.program),
        device_identification: DEV_ID,
        diagnostic_counters: Object.assign({}, counters),
    };
}
function dumpState() {
    if (!opts.state) return;
    try {
        const tmp = opts.state + ".tmp";
        fs.writeFileSync(tmp, JSON.stringify(stateObject(), null, 2) + "\n");
        fs.renameSync(tmp, opts.state);
    } catch (e) {
        process.stderr.write("state dump failed: " + e.message + "\n");
    }
}

let exiting = false;
function shutdown() {
    if (exiting) return;
    exiting = true;
    dumpState();
    try { server.close(() => {}); } catch (e) { /* ignore */ }
    process.exit(0);
}
process.on("SIGUSR1", dumpState);
process.on("SIGTERM", shutdown);
process.on("SIGINT", shutdown);
process.on("uncaughtException", (e) => {
    process.stderr.write("uncaught: " + (e && e.stack) + "\n");   // never die on one bad frame
});

server.on("initialized", () => {
    const a = server._server.address();
    process.stdout.write("listening tcp " + a.address + ":" + a.port + "\n");
});

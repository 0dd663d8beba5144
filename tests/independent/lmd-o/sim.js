#!/usr/bin/env node
'use strict';
// Lexium MDrive (LMD) Ethernet - Modbus/TCP drive simulator.
// Built on jsmodbus 5.0.0 (ModbusTCPServer / ModbusServerClient / request+response bodies).
// Manual: LMD-MODBUS-REV-D "MODBUS/TCP Fieldbus manual". See DECISIONS.md for every
// place where the manual was wrong/silent or where the library behaviour was changed.

const net = require('net');
const fs = require('fs');
const { EventEmitter } = require('events');
const jsmodbus = require('jsmodbus');

const ModbusTCPServer = jsmodbus.ModbusTCPServer;
const ModbusTCPResponse = jsmodbus.ModbusTCPResponse;
const R = jsmodbus.responses;

// ---------------------------------------------------------------- arguments
function parseArgs(argv) {
  const o = { listen: null, state: null };
  for (let i = 2; i < argv.length; i++) {
    const a = argv[i];
    if (a === '--listen') o.listen = argv[++i];
    else if (a === '--state') o.state = argv[++i];
    else if (a === '--help' || a === '-h') {
      process.stdout.write('usage: node sim.js --listen 127.0.0.1:PORT [--state FILE]\n');
      process.exit(0);
    } else {
      process.stderr.write(`unknown argument: ${a}\n`);
      process.exit(2);
    }
  }
  if (!o.listen) { process.stderr.write('--listen HOST:PORT is required (this drive is Modbus/TCP only)\n'); process.exit(2); }
  return o;
}
const args = parseArgs(process.argv);

// ---------------------------------------------------------------- helpers
const I32_MIN = -2147483648, I32_MAX = 2147483647;
const wrap32 = (v) => { v = Math.trunc(v); return ((v % 4294967296) + 4294967296) % 4294967296 | 0; };
const EXC = { ILLEGAL_FUNCTION: 1, ILLEGAL_ADDRESS: 2, ILLEGAL_VALUE: 3, DEVICE_FAILURE: 4 };
class ModbusError extends Error { constructor(code) { super('modbus exception ' + code); this.code = code; } }

// ---------------------------------------------------------------- register map (manual section 5)
// n: number of 16-bit registers (1, or 2 = 32-bit with the LOW word at the lower address,
//    see DECISIONS D3). acc: RW / RO / WO. signed only matters for 32-bit values.
const MS_VALUES = [1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127];
const REGS = [
  { a: 0x0000, n: 2, m: 'A', acc: 'RW', min: 91, max: 1525878997, def: 1000000 },
  { a: 0x0004, n: 1, m: 'BY', acc: 'RO', def: 0 },
  { a: 0x0005, n: 2, m: 'C1', acc: 'RW', signed: true, min: I32_MIN, max: I32_MAX, def: 0 },
  { a: 0x0007, n: 2, m: 'C2', acc: 'RW', signed: true, min: I32_MIN, max: I32_MAX, def: 0 },
  { a: 0x0009, n: 1, m: 'CE', acc: 'RW', min: 0, max: 1, def: 1 },
  { a: 0x000E, n: 1, m: 'CW', acc: 'RW', min: 0, max: 255, def: 10 },
  { a: 0x000F, n: 1, m: 'D1', acc: 'RW', min: 0, max: 255, def: 0 },
  { a: 0x0010, n: 1, m: 'D2', acc: 'RW', min: 0, max: 255, def: 0 },
  { a: 0x0011, n: 1, m: 'D3', acc: 'RW', min: 0, max: 255, def: 0 },
  { a: 0x0012, n: 1, m: 'D4', acc: 'RW', min: 0, max: 255, def: 0 },
  { a: 0x0013, n: 1, m: 'D5', acc: 'RW', min: 0, max: 255, def: 0 },
  { a: 0x0018, n: 2, m: 'D', acc: 'RW', min: 91, max: 1525878997, def: 1000000 },
  { a: 0x001A, n: 1, m: 'DB', acc: 'RW', min: 0, max: 65000, def: 10 },
  { a: 0x001B, n: 1, m: 'DC', acc: 'WO' },
  { a: 0x001C, n: 1, m: 'DE', acc: 'RW', min: 0, max: 1, def: 1 },
  { a: 0x001E, n: 1, m: 'EE', acc: 'RW', min: 0, max: 1, def: 0 },
  { a: 0x001F, n: 1, m: 'EF', acc: 'RO', def: 0 },
  { a: 0x0021, n: 1, m: 'ER', acc: 'RW', min: 0, max: 0, def: 0 },
  { a: 0x0024, n: 1, m: 'FC', acc: 'RW', min: 0, max: 9, def: 0 },
  { a: 0x0029, n: 1, m: 'HC', acc: 'RW', min: 0, max: 100, def: 5 },
  { a: 0x002A, n: 1, m: 'HI', acc: 'WO', min: 1, max: 4 },
  { a: 0x002B, n: 1, m: 'HM', acc: 'WO', min: 1, max: 4 },
  { a: 0x002C, n: 1, m: 'HT', acc: 'RW', min: 0, max: 65535, def: 500 },
  { a: 0x002D, n: 1, m: 'I1', acc: 'RO' },
  { a: 0x002E, n: 1, m: 'I2', acc: 'RO' },
  { a: 0x002F, n: 1, m: 'I3', acc: 'RO' },
  { a: 0x0030, n: 1, m: 'I4', acc: 'RO' },
  { a: 0x0031, n: 1, m: 'I5', acc: 'RO' },
  { a: 0x0032, n: 1, m: 'I6', acc: 'RO' },
  { a: 0x0037, n: 1, m: 'IC', acc: 'WO' },
  { a: 0x003B, n: 1, m: 'IN', acc: 'RO' },
  { a: 0x003C, n: 1, m: 'IP', acc: 'WO' },
  { a: 0x003F, n: 1, m: 'JE', acc: 'RW', min: 0, max: 1, def: 0 },
  { a: 0x0042, n: 1, m: 'LM', acc: 'RW', min: 1, max: 6, def: 1 },
  { a: 0x0043, n: 2, m: 'MA', acc: 'WO', signed: true, min: I32_MIN, max: I32_MAX },
  { a: 0x0045, n: 1, m: 'MP', acc: 'RO', def: 0 },
  { a: 0x0046, n: 2, m: 'MR', acc: 'WO', signed: true, min: I32_MIN, max: I32_MAX },
  { a: 0x0048, n: 1, m: 'MS', acc: 'RW', set: MS_VALUES, def: 256 },
  { a: 0x0049, n: 1, m: 'MT', acc: 'RW', min: 0, max: 65000, def: 0 },
  { a: 0x004A, n: 1, m: 'MV', acc: 'RO', def: 0 },
  { a: 0x004B, n: 1, m: 'O1', acc: 'RW', min: 0, max: 1 },
  { a: 0x004C, n: 1, m: 'O2', acc: 'RW', min: 0, max: 1 },
  { a: 0x004D, n: 1, m: 'O3', acc: 'RW', min: 0, max: 1 },
  { a: 0x004E, n: 1, m: 'OF', acc: 'RO', def: 0 },
  { a: 0x0056, n: 1, m: 'OT', acc: 'RW', min: 0, max: 15 },
  { a: 0x0057, n: 2, m: 'P', acc: 'RW', signed: true, min: I32_MIN, max: I32_MAX, def: 0 },
  { a: 0x0059, n: 2, m: 'PC', acc: 'RO', signed: true, def: 0 },
  { a: 0x005C, n: 1, m: 'PM', acc: 'RW', min: 0, max: 1, def: 0 },
  { a: 0x005F, n: 2, m: 'R1', acc: 'RW', signed: true, min: I32_MIN, max: I32_MAX, def: 0 },
  { a: 0x0061, n: 2, m: 'R2', acc: 'RW', signed: true, min: I32_MIN, max: I32_MAX, def: 0 },
  { a: 0x0063, n: 2, m: 'R3', acc: 'RW', signed: true, min: I32_MIN, max: I32_MAX, def: 0 },
  { a: 0x0065, n: 2, m: 'R4', acc: 'RW', signed: true, min: I32_MIN, max: I32_MAX, def: 0 },
  { a: 0x0067, n: 1, m: 'RC', acc: 'RW', min: 1, max: 100, def: 25 },
  { a: 0x0076, n: 1, m: 'S', acc: 'WO' },
  { a: 0x0077, n: 1, m: 'SF', acc: 'RW', min: 0, max: 65000, def: 15 },
  { a: 0x0078, n: 2, m: 'SL', acc: 'WO', signed: true, min: -5000000, max: 5000000 },
  { a: 0x007A, n: 1, m: 'SM', acc: 'RW', min: 0, max: 1, def: 0 },
  { a: 0x007B, n: 1, m: 'ST', acc: 'RW', min: 0, max: 0, def: 0 },
  { a: 0x007D, n: 1, m: 'TE', acc: 'RW', min: 0, max: 43, def: 0 },
  { a: 0x0085, n: 2, m: 'V', acc: 'RO', signed: true, def: 0 },
  { a: 0x0088, n: 1, m: 'VC', acc: 'RO', def: 0 },
  { a: 0x0089, n: 2, m: 'VI', acc: 'RW', min: 1, max: 2559999, def: 1000 },
  { a: 0x008B, n: 2, m: 'VM', acc: 'RW', min: 2, max: 2560000, def: 768000 },
  { a: 0x008D, n: 1, m: 'WT', acc: 'RW', min: 0, max: 84, def: 80 },
  // 5.1 hMTechnology (closed loop; this simulated unit is a closed-loop model)
  { a: 0x008E, n: 1, m: 'AS', acc: 'RW', min: 0, max: 3, def: 2 },
  { a: 0x008F, n: 1, m: 'AF', acc: 'RO', def: 128 },
  { a: 0x0091, n: 1, m: 'CB', acc: 'RW', min: 0, max: 3, def: 1 },
  { a: 0x0093, n: 1, m: 'CF', acc: 'WO' },
  { a: 0x0095, n: 2, m: 'LD', acc: 'RW', min: 0, max: I32_MAX, def: 102400 },
  { a: 0x0097, n: 2, m: 'LG', acc: 'RW', min: 0, max: I32_MAX, def: 102400 },
  { a: 0x0099, n: 2, m: 'LL', acc: 'RO', signed: true, def: 0 },
  { a: 0x009B, n: 1, m: 'LR', acc: 'RO', def: 0 },
  { a: 0x009C, n: 2, m: 'LT', acc: 'RW', min: 2, max: 65535, def: 2000 },
  { a: 0x009E, n: 2, m: 'MF', acc: 'RW', min: 306, max: 2560000, def: 768000 },
  { a: 0x00A0, n: 1, m: 'MU', acc: 'RW', min: 0, max: 2, def: 0 },
  { a: 0x00A1, n: 1, m: 'SC', acc: 'WO' },
  { a: 0x00A3, n: 2, m: 'TS', acc: 'RW', min: 0, max: 255, def: 0 },
  { a: 0x00A5, n: 1, m: 'TD', acc: 'RW', min: 0, max: 1, def: 1 },
  { a: 0x00A6, n: 1, m: 'TQ', acc: 'RW', min: 1, max: 100, def: 25 },
  { a: 0x00A7, n: 1, m: 'VF', acc: 'RW', min: 0, max: 1000, def: 0 },
  // 5.2 user variables
  ...[1, 2, 3, 4, 5, 6, 7, 8].map((i) => ({ a: 0x00A8 + (i - 1) * 2, n: 2, m: 'V' + i, acc: 'RW', signed: true, min: I32_MIN, max: I32_MAX, def: 0 })),
];
const LAST_ADDR = 0x00B7;
const BY_ADDR = new Map();   // register address -> { reg, half }
for (const r of REGS) for (let h = 0; h < r.n; h++) BY_ADDR.set(r.a + h, { reg: r, half: h });
const BY_MN = new Map(REGS.map((r) => [r.m, r]));
// Parameters that are saved by S / restored by IP (RW configuration, not live/motion data).
const SAVED = REGS.filter((r) => r.acc === 'RW' && !['C1', 'C2', 'P', 'ER', 'ST', 'O1', 'O2', 'O3', 'OT'].includes(r.m)).map((r) => r.m);

// ---------------------------------------------------------------- device state
const dev = {
  p: {},                 // mnemonic -> value (register backed parameters)
  outputs: 0,            // bit0..3 = outputs 1..4
  inputs: 0,             // bit0..3 = inputs 1..4 (simulated: nothing wired)
  analog: 0,             // I5 counts
  index: 0,              // I6
  mfg: {},               // manufacturer specific parameters (FC 65/66), mnemonic(+point) -> string
  nvm: null,             // image saved by S (register params + mfg params)
  program: { running: false, paused: false },
};
const MFG_DEFAULTS = {
  AO: '0', EL: '1000', MU: '0,0', RD: '0', AJ: '128', AT: '0', BE: '0', BL: '0', BM: '0',
  DJ: '128', DT: '0', FS: '0', FL: '0', LS: '0,0,0', TR: '0,0,0',
  SK1: '0', SK2: '0', SK3: '0', SK4: '0',
  IS1: '1,0,0', IS2: '2,0,0', IS3: '3,0,0', IS4: '4,0,0', IS5: '5,9,0',
  OS1: '1,16,0', OS2: '2,17,0', OS3: '3,18,0',
};
function setDefaults() {
  for (const r of REGS) if (r.def !== undefined) dev.p[r.m] = r.def;
  dev.mfg = Object.assign({}, MFG_DEFAULTS);
  dev.outputs = 0;
}
setDefaults();
dev.nvm = { params: Object.fromEntries(SAVED.map((m) => [m, dev.p[m]])), mfg: Object.assign({}, dev.mfg) };

// ---------------------------------------------------------------- motion simulation
const motion = { active: false, kind: null, target: 0, vel: 0, slew: 0, homeEnd: 0, frac: 0 };
let motionTimer = null;
const TICK_MS = 10;
function startMotion(kind, value) {
  motion.kind = kind;
  if (kind === 'abs') motion.target = value;
  else if (kind === 'rel') motion.target = dev.p.P + value;
  else if (kind === 'slew') motion.slew = value;
  else if (kind === 'home') { motion.target = 0; motion.homeEnd = Date.now() + 300; }
  motion.active = true;
  dev.p.MV = 1; dev.p.MP = (kind === 'abs' || kind === 'rel') ? 1 : 0;
  if (!motionTimer) motionTimer = setInterval(motionTick, TICK_MS);
}
function stopMotion() {
  motion.active = false; motion.vel = 0; motion.frac = 0;
  dev.p.MV = 0; dev.p.MP = 0; dev.p.VC = 0; dev.p.V = 0;
  if (motionTimer) { clearInterval(motionTimer); motionTimer = null; }
}
function motionTick() {
  const dt = TICK_MS / 1000;
  const vm = dev.p.VM, acc = dev.p.A, dec = dev.p.D, vi = Math.min(dev.p.VI, vm);
  let v = motion.vel;
  let desired;
  if (motion.kind === 'slew') desired = motion.slew;
  else {
    const rem = motion.target - dev.p.P;
    if (rem === 0 && Math.abs(v) <= vi) { finishMove(); return; }
    const dir = Math.sign(rem) || Math.sign(v);
    const stopDist = (v * v - vi * vi) / (2 * dec);
    desired = (Math.abs(rem) <= stopDist && Math.sign(v) === dir) ? dir * vi : dir * vm;
  }
  const prev = v;
  if (v === 0 && desired !== 0) v = Math.sign(desired) * Math.min(vi, Math.abs(desired));
  if (desired > v) v = Math.min(desired, v + (v >= 0 ? acc : dec) * dt);
  else if (desired < v) v = Math.max(desired, v - (v <= 0 ? acc : dec) * dt);
  if (motion.kind === 'slew' && desired === 0 && Math.abs(v) <= vi) { finishMove(); return; }
  let step = v * dt + motion.frac;
  let whole = Math.trunc(step);
  motion.frac = step - whole;
  if (motion.kind !== 'slew') {
    const rem = motion.target - dev.p.P;
    if (Math.abs(whole) >= Math.abs(rem) || Math.sign(whole) !== Math.sign(rem)) {
      if (Math.abs(whole) >= Math.abs(rem)) { whole = rem; }
    }
  }
  dev.p.P = wrap32(dev.p.P + whole);
  dev.p.C1 = wrap32(dev.p.C1 + whole);
  if (dev.p.EE) dev.p.C2 = wrap32(dev.p.C2 + whole);
  motion.vel = v;
  dev.p.V = Math.round(v);
  dev.p.VC = (v !== prev) ? 1 : 0;
  if (motion.kind !== 'slew' && dev.p.P === motion.target) { finishMove(); }
}
function finishMove() {
  if (motion.kind === 'home') { dev.p.P = 0; dev.p.C1 = 0; if (dev.p.EE) dev.p.C2 = 0; }
  stopMotion();
}

// ---------------------------------------------------------------- register read / write
function regRawValue(r) {
  switch (r.m) {
    case 'I1': case 'I2': case 'I3': case 'I4': return (dev.inputs >> (Number(r.m[1]) - 1)) & 1;
    case 'I5': return dev.analog;
    case 'I6': return dev.index;
    case 'IN': return dev.inputs & 15;
    case 'O1': case 'O2': case 'O3': return (dev.outputs >> (Number(r.m[1]) - 1)) & 1;
    case 'OT': return dev.outputs & 15;
    case 'BY': return dev.program.running ? 1 : 0;
    default: return dev.p[r.m] !== undefined ? dev.p[r.m] : 0;
  }
}
function regWords(r) {
  const v = regRawValue(r);
  if (r.n === 1) return [v & 0xFFFF];
  const u = v >>> 0;
  return [u & 0xFFFF, (u >>> 16) & 0xFFFF];  // low word first (manual 4.2.4/4.2.5 examples)
}

function readHolding(start, count) {
  // manual 4.2.4: quantity 1 to 2 (see DECISIONS D4)
  if (count < 1 || count > 2) throw new ModbusError(EXC.ILLEGAL_VALUE);
  if (start + count - 1 > LAST_ADDR) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  const out = [];
  for (let a = start; a < start + count; a++) {
    const e = BY_ADDR.get(a);
    if (!e || e.reg.acc === 'WO') throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  }
  const seen = new Set();
  for (let a = start; a < start + count; a++) {
    const e = BY_ADDR.get(a);
    out.push(regWords(e.reg)[e.half]);
    seen.add(e.reg);
  }
  // ER: "must be read or set to 0 to clear" (read clears, after the value was returned)
  for (const r of seen) if (r.m === 'ER' && dev.p.ER !== 0) { dev.p.ER = 0; dev.p.EF = 0; }
  return out;
}

function toValue(r, words) {
  if (r.n === 1) return words[0];
  const u = ((words[1] << 16) | words[0]) >>> 0;
  return r.signed ? (u | 0) : u;
}

function checkRange(r, v, pending) {
  if (r.set) return r.set.includes(v);
  if (r.min !== undefined && v < r.min) return false;
  if (r.max !== undefined && v > r.max) return false;
  const get = (m) => (pending[m] !== undefined ? pending[m] : dev.p[m]);
  if (r.m === 'VI' && v >= get('VM')) return false;       // 1 .. VM-1
  if (r.m === 'VM' && v <= get('VI')) return false;       // VI+1 .. 2560000
  if (r.m === 'HT' && v === 1) return false;              // 0 or 2..65535
  if (r.m === 'HT' && v + get('MT') > 65535) return false;
  if (r.m === 'MT' && v + get('HT') > 65535) return false;
  if ((r.m === 'DC' || r.m === 'IC') && !INCDEC_TARGETS.has(v)) return false;
  return true;
}
// DC / IC: value = holding register address (low word) of the variable to step (DECISIONS D9)
const INCDEC_TARGETS = new Map(['C1', 'C2', 'P', 'R1', 'R2', 'R3', 'R4', 'V1', 'V2', 'V3', 'V4', 'V5', 'V6', 'V7', 'V8'].map((m) => [BY_MN.get(m).a, m]));

function writeHolding(start, words) {
  const count = words.length;
  if (count < 1 || count > 2) throw new ModbusError(EXC.ILLEGAL_VALUE);
  if (start + count - 1 > LAST_ADDR) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  // address phase: every register must exist, be writable, and whole parameters must be covered
  const items = [];
  let a = start;
  while (a < start + count) {
    const e = BY_ADDR.get(a);
    if (!e) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
    if (e.reg.acc === 'RO') throw new ModbusError(EXC.ILLEGAL_ADDRESS);
    if (e.half !== 0 || a + e.reg.n > start + count) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
    items.push({ r: e.reg, words: words.slice(a - start, a - start + e.reg.n) });
    a += e.reg.n;
  }
  // value phase (all values checked before anything is applied)
  const pending = {};
  for (const it of items) {
    it.v = toValue(it.r, it.words);
    if (!checkRange(it.r, it.v, pending)) throw new ModbusError(EXC.ILLEGAL_VALUE);
    if (it.r.acc === 'RW') pending[it.r.m] = it.v;
  }
  for (const it of items) applyWrite(it.r, it.v);
}

function applyWrite(r, v) {
  switch (r.m) {
    case 'O1': case 'O2': case 'O3': {
      const bit = 1 << (Number(r.m[1]) - 1);
      dev.outputs = v ? (dev.outputs | bit) : (dev.outputs & ~bit);
      return;
    }
    case 'OT': dev.outputs = v & 15; return;
    case 'ER': dev.p.ER = 0; dev.p.EF = 0; return;
    case 'MU': dev.p.MU = v; dev.mfg.MU = `${v},${dev.mfg.MU.split(',')[1] || 0}`; return;
    case 'MA': startMotion('abs', v); return;
    case 'MR': startMotion('rel', v); return;
    case 'SL': if (v === 0 && !motion.active) return; startMotion('slew', v); return;
    case 'HI': case 'HM': startMotion('home', v); return;
    case 'DC': case 'IC': {
      const m = INCDEC_TARGETS.get(v);
      dev.p[m] = wrap32(dev.p[m] + (r.m === 'IC' ? 1 : -1));
      return;
    }
    case 'IP':
      if (motion.active) stopMotion();
      Object.assign(dev.p, dev.nvm.params);
      Object.assign(dev.mfg, dev.nvm.mfg);
      return;
    case 'S':
      dev.nvm = { params: Object.fromEntries(SAVED.map((m) => [m, dev.p[m]])), mfg: Object.assign({}, dev.mfg) };
      return;
    case 'CF': dev.p.LR = 0; return;
    case 'SC': return; // configuration test: nothing observable in the register map
    default: dev.p[r.m] = v;
  }
}

// ---------------------------------------------------------------- coils / discrete inputs (4 points)
function checkBitRange(start, qty) {
  if (qty < 1 || qty > 0x07D0) throw new ModbusError(EXC.ILLEGAL_VALUE);
  if (start + qty > 4) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
}
function bitsOf(word, start, qty) { const a = []; for (let i = 0; i < qty; i++) a.push((word >> (start + i)) & 1); return a; }

// ---------------------------------------------------------------- manufacturer specific (FC 65 / 66)
// spec: { acc, fields: [[min,max]|'set'...] } ; value stored as canonical "a,b,c" string
const int = (min, max) => ({ min, max });
const MFG = {
  '\x1B': { acc: 'WO', cmd: true },                    // <ESC>
  E: { acc: 'WO', cmd: true },
  CP: { acc: 'WO', cmd: true },
  PS: { acc: 'WO', cmd: true },
  RS: { acc: 'WO', cmd: true },
  EX: { acc: 'WO', label: true },
  HF: { acc: 'WO', fields: [int(1, 4)] },
  UG: { acc: 'WO', fields: [int(2956102, 2956102)] },
  AO: { acc: 'RW', fields: [int(0, 65535)] },
  EL: { acc: 'RW', fields: [int(1, 65535)] },
  MU: { acc: 'RW', fields: [int(0, 2), int(0, 1)] },
  RD: { acc: 'RW', fields: [int(0, 1)] },
  AJ: { acc: 'RW', fields: [int(1, 999)] },
  DJ: { acc: 'RW', fields: [int(1, 999)] },
  AT: { acc: 'RW', fields: [int(0, 1)] },
  DT: { acc: 'RW', fields: [int(0, 1)] },
  BE: { acc: 'RW', fields: [int(0, 1)] },
  BM: { acc: 'RW', fields: [int(0, 1)] },
  BL: { acc: 'RW', fields: [int(0, I32_MAX)] },
  FS: { acc: 'RW', fields: [int(0, 65535)] },
  FL: { acc: 'RW', fields: [int(0, 1)] },
  LS: { acc: 'RW', fields: [int(0, 1), int(I32_MIN, I32_MAX), int(0, 1)] },
  TR: { acc: 'RW', fields: [int(I32_MIN, I32_MAX), int(0, 1), int(0, 1)] },
  IS: { acc: 'RW', io: 'in' },
  S: { acc: 'RW', io: 'in' },            // S1..S4 short form (example in 4.3.2)
  OS: { acc: 'RW', io: 'out' },
  IT: { acc: 'RO', ro: () => '52,37' },
  VT: { acc: 'RO', ro: () => '24,24' },
  AV: { acc: 'RO', ro: () => String(dev.p.V) },
};
const IN_TYPES = [0, 1, 2, 3, 5, 7, 8, 11, 12];
const OUT_TYPES = [16, 17, 18, 20, 21, 23, 24, 25, 28, 29];

function decodeMnemonic(b) {
  // The four mnemonic bytes carry the ASCII mnemonic in reverse order, padded with 0x20 (or 0x00).
  const s = Buffer.from([b[3], b[2], b[1], b[0]]).toString('latin1').replace(/[ \x00]/g, '');
  if (s === '\x1B') return { name: '\x1B', point: null };
  const m = /^([A-Z]{1,2})([1-5])?$/.exec(s);
  if (!m) return null;
  return { name: m[1], point: m[2] ? Number(m[2]) : null };
}
function parseInts(str) {
  if (!/^[+-]?\d+(,[+-]?\d+)*$/.test(str)) return null;
  return str.split(',').map(Number);
}
function checkFields(fields, vals) {
  if (!vals || vals.length !== fields.length) return false;
  return fields.every((f, i) => Number.isSafeInteger(vals[i]) && vals[i] >= f.min && vals[i] <= f.max);
}

function mfgRead(mn) {
  const spec = MFG[mn.name];
  if (!spec) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  if (spec.acc === 'WO') throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  if (spec.io) return ioRead(spec, mn);
  if (mn.point !== null) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  if (spec.ro) return spec.ro();
  if (mn.name === 'MU') return `${dev.p.MU},${dev.mfg.MU.split(',')[1]}`;
  return dev.mfg[mn.name];
}
function ioRead(spec, mn) {
  const p = mn.point;
  if (spec.io === 'in') {
    if (p === null || p > 5 || (mn.name === 'S' && p > 4)) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
    const v = dev.mfg['IS' + p];
    return mn.name === 'S' ? v.split(',').slice(1).concat([dev.mfg['SK' + p] || '0']).join(',') : v;
  }
  if (p === null || p > 3) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  return dev.mfg['OS' + p];
}

function mfgWrite(mn, data) {
  const spec = MFG[mn.name];
  if (!spec) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  if (spec.acc === 'RO') throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  if (!spec.io && mn.point !== null) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  // parameter string: "=" (or a blank, see EX / UG examples) followed by the value(s)
  let s = data.toString('latin1').replace(/[\r\n\x00]+$/, '');
  if (spec.cmd) {
    if (s.replace(/[ =]/g, '') !== '') throw new ModbusError(EXC.ILLEGAL_VALUE);
    return mfgCommand(mn.name);
  }
  s = s.replace(/^[ ]*=?[ ]*/, '').replace(/\s+$/, '').replace(/\s*,\s*/g, ',');
  if (spec.label) {
    if (!/^([A-Za-z][A-Za-z0-9]?|\d{1,4})$/.test(s)) throw new ModbusError(EXC.ILLEGAL_VALUE);
    dev.program.running = true; dev.program.paused = false;
    setTimeout(() => { dev.program.running = false; dev.program.paused = false; }, 200).unref();
    return;
  }
  const vals = parseInts(s);
  if (spec.io) return ioWrite(spec, mn, vals);
  if (!checkFields(spec.fields, vals)) throw new ModbusError(EXC.ILLEGAL_VALUE);
  switch (mn.name) {
    case 'HF': if (!motion.active) startMotion('home', vals[0]); return;
    case 'UG': return; // see DECISIONS D15
    case 'MU':
      dev.p.MU = vals[0];
      if (vals[1] === 1) dev.p.LL = 0;
      dev.mfg.MU = `${vals[0]},${vals[1]}`;
      return;
    default: dev.mfg[mn.name] = vals.join(',');
  }
}
function ioWrite(spec, mn, vals) {
  if (!vals) throw new ModbusError(EXC.ILLEGAL_VALUE);
  if (spec.io === 'in') {
    if (mn.name === 'S') {           // S<n>=type,active[,sink/source]
      if (mn.point === null || mn.point > 4) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
      if (vals.length < 2 || vals.length > 3) throw new ModbusError(EXC.ILLEGAL_VALUE);
      if (vals.length === 3 && !(vals[2] === 0 || vals[2] === 1)) throw new ModbusError(EXC.ILLEGAL_VALUE);
      var sink = vals.length === 3 ? String(vals[2]) : null;
      vals = [mn.point, vals[0], vals[1]];
    } else if (mn.point !== null) {
      vals = vals.length === 2 ? [mn.point].concat(vals) : vals;
    }
    if (vals.length !== 3) throw new ModbusError(EXC.ILLEGAL_VALUE);
    const [line, b, c] = vals;
    if (mn.point !== null && line !== mn.point) throw new ModbusError(EXC.ILLEGAL_VALUE);
    if (line >= 1 && line <= 4) {
      if (!IN_TYPES.includes(b) || !(c === 0 || c === 1)) throw new ModbusError(EXC.ILLEGAL_VALUE);
    } else if (line === 5) {         // analog input: mode 9 (voltage) / 10 (current), range 0/1
      if (!(b === 9 || b === 10) || !(c === 0 || c === 1)) throw new ModbusError(EXC.ILLEGAL_VALUE);
    } else throw new ModbusError(EXC.ILLEGAL_VALUE);
    dev.mfg['IS' + line] = `${line},${b},${c}`;
    if (mn.name === 'S' && sink !== null) dev.mfg['SK' + line] = sink;
    return;
  }
  if (mn.point !== null && vals.length === 2) vals = [mn.point].concat(vals);
  if (vals.length !== 3) throw new ModbusError(EXC.ILLEGAL_VALUE);
  const [line, b, c] = vals;
  if (mn.point !== null && line !== mn.point) throw new ModbusError(EXC.ILLEGAL_VALUE);
  if (line < 1 || line > 3 || !OUT_TYPES.includes(b) || !(c === 0 || c === 1)) throw new ModbusError(EXC.ILLEGAL_VALUE);
  if (b === 28 && line !== 3) throw new ModbusError(EXC.ILLEGAL_VALUE);   // Trip: output 3 only
  dev.mfg['OS' + line] = `${line},${b},${c}`;
}
function mfgCommand(name) {
  switch (name) {
    case '\x1B': if (motion.active) stopMotion(); dev.program.running = false; dev.program.paused = false; return;
    case 'E': dev.program.running = false; dev.program.paused = false; return;
    case 'CP': dev.program.running = false; dev.program.paused = false; return;
    case 'PS': if (dev.program.running) dev.program.paused = true; return;
    case 'RS': dev.program.paused = false; return;
  }
}

// FC 65 request PDU: 41 hi hi lo lo  -> 41 N <N ascii bytes>
function handleFC65(pdu) {
  if (pdu.length !== 5) throw new ModbusError(EXC.ILLEGAL_VALUE);
  const mn = decodeMnemonic(pdu.subarray(1, 5));
  if (!mn) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  const str = Buffer.from(mfgRead(mn), 'latin1');
  return Buffer.concat([Buffer.from([0x41, str.length]), str]);
}
// FC 66 request PDU: 42 hi hi lo lo N <N bytes>  -> 42 04 hi hi lo lo
function handleFC66(pdu) {
  if (pdu.length < 6) throw new ModbusError(EXC.ILLEGAL_VALUE);
  const n = pdu[5];
  if (n > 28 || pdu.length !== 6 + n) throw new ModbusError(EXC.ILLEGAL_VALUE);
  const mn = decodeMnemonic(pdu.subarray(1, 5));
  if (!mn) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  mfgWrite(mn, pdu.subarray(6, 6 + n));
  return Buffer.concat([Buffer.from([0x42, 0x04]), pdu.subarray(1, 5)]);
}

// ---------------------------------------------------------------- device identification (FC 43/14)
const DEVICE_ID = [
  'IMS USA',                 // 0x00 VendorName
  'LMDCE572',                // 0x01 ProductCode ("LMDxExxx": closed-loop Ethernet LMD)
  '4.0.0.0',                 // 0x02 MajorMinorRevision
  'https://novantaims.com/', // 0x03 VendorUrl
  'LMD Ethernet',            // 0x04 ProductName
  '269100001',               // 0x05 ModelName (manual: serial number)
  'LMDCM 6.010, Hw: 1.0',    // 0x06 UserApplicationName
].map((s) => Buffer.from(s, 'latin1'));

function deviceIdObjects(code, objectId) {
  if (code === 4) {
    if (objectId >= DEVICE_ID.length) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
    return { objects: [objectId], level: code };
  }
  const last = code === 1 ? 2 : DEVICE_ID.length - 1;      // basic 0-2; regular/extended 0-6
  const first = (objectId <= last) ? objectId : 0;         // unknown id in stream access -> restart at 0
  const ids = []; for (let i = first; i <= last; i++) ids.push(i);
  return { objects: ids, level: code };
}

// ---------------------------------------------------------------- jsmodbus server (library side)
// The library only sees frames that the front end (below) has already validated. Its data buffers
// are disabled (null) so every standard request is routed to our event handlers, where the
// responses are built with the library's own response bodies.
const hub = new EventEmitter();
const mbServer = new ModbusTCPServer(hub, { coils: null, discrete: null, holding: null, input: null });
const counters = { bus_messages: 0, exception_responses: 0, dropped_frames: 0, connections: 0 };

function reply(request, cb, body) { cb(ModbusTCPResponse.fromRequest(request, body).createPayload()); }
function guarded(fn) {
  return (request, cb) => {
    try { fn(request, cb); } catch (e) {
      const code = e instanceof ModbusError ? e.code : EXC.DEVICE_FAILURE;
      counters.exception_responses++;
      reply(request, cb, new R.ExceptionResponseBody(request.body.fc, code));
    }
  };
}
mbServer.on('readCoils', guarded((req, cb) => {
  checkBitRange(req.body.start, req.body.count);
  const bits = bitsOf(dev.outputs, req.body.start, req.body.count);
  reply(req, cb, new R.ReadCoilsResponseBody(bits, Math.ceil(bits.length / 8)));
}));
mbServer.on('readDiscreteInputs', guarded((req, cb) => {
  checkBitRange(req.body.start, req.body.count);
  const bits = bitsOf(dev.inputs, req.body.start, req.body.count);
  reply(req, cb, new R.ReadDiscreteInputsResponseBody(bits, Math.ceil(bits.length / 8)));
}));
mbServer.on('writeSingleCoil', guarded((req, cb) => {
  // value already checked (0x0000 / 0xFF00) by the front end
  if (req.body.address > 3) throw new ModbusError(EXC.ILLEGAL_ADDRESS);
  const bit = 1 << req.body.address;
  dev.outputs = req.body.value === 0xFF00 ? (dev.outputs | bit) : (dev.outputs & ~bit);
  reply(req, cb, R.WriteSingleCoilResponseBody.fromRequest(req.body));
}));
mbServer.on('readHoldingRegisters', guarded((req, cb) => {
  const words = readHolding(req.body.start, req.body.count);
  const buf = Buffer.alloc(words.length * 2);
  words.forEach((w, i) => buf.writeUInt16BE(w, i * 2));
  reply(req, cb, new R.ReadHoldingRegistersResponseBody(buf.length, buf));
}));
mbServer.on('writeMultipleRegisters', guarded((req, cb) => {
  writeHolding(req.body.address, req.body.valuesAsArray);
  reply(req, cb, R.WriteMultipleRegistersResponseBody.fromRequest(req.body));
}));
mbServer.on('readDeviceIdentification', guarded((req, cb) => {
  const { objects } = deviceIdObjects(req.body.readDeviceIdCode, req.body.objectId);
  const objs = objects.map((id) => ({ id, value: DEVICE_ID[id] }));
  reply(req, cb, new R.ReadDeviceIdentificationResponseBody(req.body.readDeviceIdCode, 0x82, 0x00, 0x00, objs));
}));

// ---------------------------------------------------------------- front end: MBAP framing + PDU checks
const SUPPORTED = new Set([0x01, 0x02, 0x03, 0x05, 0x10, 0x2B, 0x41, 0x42]);
const MAX_BUFFER = 8192;

function rawException(header, fc, code) {
  counters.exception_responses++;
  const out = Buffer.alloc(9);
  header.copy(out, 0, 0, 4);
  out.writeUInt16BE(3, 4); out[6] = header[6]; out[7] = (fc | 0x80) & 0xFF; out[8] = code;
  return out;
}
function rawResponse(header, pdu) {
  const out = Buffer.alloc(7 + pdu.length);
  header.copy(out, 0, 0, 4);
  out.writeUInt16BE(pdu.length + 1, 4); out[6] = header[6]; pdu.copy(out, 7);
  return out;
}
// Returns null when the PDU may be passed to the library, or an exception code.
function precheck(pdu) {
  const fc = pdu[0];
  const len = pdu.length;
  switch (fc) {
    case 0x01: case 0x02: case 0x03:
      if (len !== 5) return EXC.ILLEGAL_VALUE;
      if (fc === 0x03) { const q = pdu.readUInt16BE(3); if (q < 1 || q > 2) return EXC.ILLEGAL_VALUE; }
      else { const q = pdu.readUInt16BE(3); if (q < 1 || q > 0x07D0) return EXC.ILLEGAL_VALUE; }
      return null;
    case 0x05: {
      if (len !== 5) return EXC.ILLEGAL_VALUE;
      const v = pdu.readUInt16BE(3);
      if (v !== 0x0000 && v !== 0xFF00) return EXC.ILLEGAL_VALUE;
      return null;
    }
    case 0x10: {
      if (len < 6) return EXC.ILLEGAL_VALUE;
      const q = pdu.readUInt16BE(3), bc = pdu[5];
      if (q < 1 || q > 2 || bc !== q * 2 || len !== 6 + bc) return EXC.ILLEGAL_VALUE;
      return null;
    }
    case 0x2B:
      if (len < 2) return EXC.ILLEGAL_VALUE;
      if (pdu[1] !== 0x0E) return EXC.ILLEGAL_FUNCTION;       // only MEI 14 is implemented
      if (len !== 4) return EXC.ILLEGAL_VALUE;
      if (pdu[2] < 1 || pdu[2] > 4) return EXC.ILLEGAL_VALUE;
      return null;
  }
  return EXC.ILLEGAL_FUNCTION;
}

function handleFrame(conn, frame) {
  const header = frame.subarray(0, 7);
  const pdu = frame.subarray(7);
  counters.bus_messages++;
  const fc = pdu[0];
  if (!SUPPORTED.has(fc)) return conn.send(rawException(header, fc, EXC.ILLEGAL_FUNCTION));
  if (fc === 0x41 || fc === 0x42) {
    try {
      return conn.send(rawResponse(header, fc === 0x41 ? handleFC65(pdu) : handleFC66(pdu)));
    } catch (e) {
      return conn.send(rawException(header, fc, e instanceof ModbusError ? e.code : EXC.DEVICE_FAILURE));
    }
  }
  const code = precheck(pdu);
  if (code !== null) return conn.send(rawException(header, fc, code));
  // hand the validated frame to the library; it answers synchronously through conn.proxy.write
  conn.answered = false;
  try {
    conn.proxy.emit('data', Buffer.from(frame));
  } catch (e) { /* fall through */ }
  if (!conn.answered) {
    // the library could not parse/answer: make sure no half frame stays in its buffer
    if (conn.lib && conn.lib._requestHandler) { conn.lib._requestHandler._buffer = Buffer.alloc(0); conn.lib._requestHandler._requests = []; }
    conn.send(rawException(header, fc, EXC.DEVICE_FAILURE));
  }
}

const sockets = new Set();
const tcp = net.createServer((sock) => {
  counters.connections++;
  sockets.add(sock);
  sock.setNoDelay(true);
  let buf = Buffer.alloc(0);
  const conn = {
    send(b) { if (!sock.destroyed && sock.writable) sock.write(b); },
    proxy: new EventEmitter(),
  };
  conn.proxy.write = (b, done) => { conn.answered = true; conn.send(b); if (typeof done === 'function') done(); return true; };
  const onLib = (c) => { conn.lib = c; };
  mbServer.once('connection', onLib);
  hub.emit('connection', conn.proxy);   // jsmodbus ModbusServerClient attaches to the proxy
  mbServer.removeListener('connection', onLib);
  sock.on('data', (chunk) => {
    buf = buf.length ? Buffer.concat([buf, chunk]) : chunk;
    let guard = 0;
    while (buf.length >= 6 && guard++ < 1000) {
      const proto = buf.readUInt16BE(2);
      const len = buf.readUInt16BE(4);
      if (len > 254) {                     // no valid Modbus ADU: stream cannot be re-synchronised
        counters.dropped_frames++;
        buf = Buffer.alloc(0);
        sock.destroy();
        return;
      }
      if (buf.length < 6 + len) break;
      const frame = buf.subarray(0, 6 + len);
      buf = buf.subarray(6 + len);
      if (proto !== 0 || len < 2) { counters.dropped_frames++; continue; }
      try { handleFrame(conn, frame); } catch (e) { counters.dropped_frames++; }
    }
    if (buf.length > MAX_BUFFER) { buf = Buffer.alloc(0); sock.destroy(); }
    else if (buf.length) buf = Buffer.from(buf);
  });
  sock.on('error', () => {});
  sock.on('close', () => { sockets.delete(sock); conn.proxy.removeAllListeners(); });
});
tcp.on('error', (e) => { process.stderr.write(`server error: ${e.message}\n`); process.exit(1); });

// ---------------------------------------------------------------- state dump
function stateObject() {
  const registers = {};
  for (const r of REGS) {
    if (r.acc === 'WO') continue;
    const key = '0x' + r.a.toString(16).toUpperCase().padStart(4, '0');
    registers[key] = { name: r.m, words: r.n, value: regRawValue(r), raw: regWords(r) };
  }
  const coils = {}; const inputs = {};
  for (let i = 0; i < 4; i++) { coils[String(i)] = (dev.outputs >> i) & 1; inputs[String(i)] = (dev.inputs >> i) & 1; }
  const mfg = {};
  for (const k of Object.keys(dev.mfg).sort()) mfg[k] = dev.mfg[k];
  mfg.MU = `${dev.p.MU},${dev.mfg.MU.split(',')[1]}`;
  return {
    device: 'Lexium MDrive LMD Ethernet (Modbus/TCP)',
    holding_registers: registers,
    coils,
    discrete_inputs: inputs,
    manufacturer_parameters: mfg,
    nvm: { params: dev.nvm.params, manufacturer_parameters: dev.nvm.mfg },
    program: { running: dev.program.running, paused: dev.program.paused },
    diagnostic_counters: Object.assign({}, counters),
  };
}
function dumpState() {
  if (!args.state) return;
  try {
    const tmp = args.state + '.tmp';
    fs.writeFileSync(tmp, JSON.stringify(stateObject(), null, 2) + '\n');
    fs.renameSync(tmp, args.state);
  } catch (e) { process.stderr.write(`state dump failed: ${e.message}\n`); }
}
let exiting = false;
function shutdown() {
  if (exiting) return; exiting = true;
  dumpState();
  for (const s of sockets) s.destroy();
  tcp.close();
  process.exit(0);
}
process.on('SIGUSR1', dumpState);
process.on('SIGTERM', shutdown);
process.on('SIGINT', shutdown);
process.on('uncaughtException', (e) => { process.stderr.write(`internal error (ignored): ${e && e.stack}\n`); });

// ---------------------------------------------------------------- listen
const m = /^(.*):(\d+)$/.exec(args.listen);
if (!m) { process.stderr.write('bad --listen value, expected HOST:PORT\n'); process.exit(2); }
const host = m[1].replace(/^\[|\]$/g, '');
tcp.listen({ host, port: Number(m[2]) }, () => {
  const ad = tcp.address();
  process.stdout.write(`listening tcp ${ad.address}:${ad.port}\n`);
});

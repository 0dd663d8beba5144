#!/usr/bin/env node
'use strict';
// SIEB & MEYER SD2x drive amplifier -- Modbus RTU slave simulator.
// Built on jsmodbus 5.0.0 (ModbusRTUServer for FC 03/04/06/16) plus our own
// front end (RTU framing, address filter, FC 08 / 23 / 43, diagnostics).
// See DECISIONS.md for every interpretation of the manual.

const net = require('net');
const fs = require('fs');
const { EventEmitter } = require('events');
const jsmodbus = require('jsmodbus');

const { ModbusRTUServer, ModbusRTUResponse } = jsmodbus;
const R = jsmodbus.responses;

// ---------------------------------------------------------------- CLI
function parseArgs(argv) {
  const o = { listen: null, serial: null, baud: 19200, parity: 'even', state: null, unit: 1 };
  for (let i = 0; i < argv.length; i++) {
    const a = argv[i];
    const next = () => {
      if (i + 1 >= argv.length) { usage(`missing value for ${a}`); }
      return argv[++i];
    };
    if (a === '--listen') o.listen = next();
    else if (a === '--serial') o.serial = next();
    else if (a === '--baud') o.baud = parseInt(next(), 10);
    else if (a === '--parity') o.parity = next().toLowerCase();
    else if (a === '--state') o.state = next();
    else if (a === '--unit') o.unit = parseInt(next(), 10);
    else usage(`unknown argument ${a}`);
  }
  if (!o.listen && !o.serial) usage('need --listen HOST:PORT or --serial DEVICE');
  if (![9600, 14400, 19200, 28800, 38400, 57600, 115200].includes(o.baud)) usage(`unsupported baud rate ${o.baud}`);
  if (!['none', 'even', 'odd'].includes(o.parity)) usage(`unsupported parity ${o.parity}`);
  if (!(o.unit >= 1 && o.unit <= 254)) usage('unit must be 1..254');
  return o;
}
function usage(msg) {
  process.stderr.write(`sim.js: ${msg}\nusage: node sim.js (--listen 127.0.0.1:PORT | --serial DEV [--baud B] [--parity none|even|odd]) [--unit 1..254] [--state FILE]\n`);
  process.exit(2);
}
const opts = parseArgs(process.argv.slice(2));
const UNIT = opts.unit;

// ---------------------------------------------------------------- CRC
function crc16(buf, len = buf.length) {
  let c = 0xFFFF;
  for (let i = 0; i < len; i++) {
    c ^= buf[i];
    for (let b = 0; b < 8; b++) c = (c & 1) ? ((c >>> 1) ^ 0xA001) : (c >>> 1);
  }
  return c;
}
function crcOk(buf, len) {
  if (len < 4 || buf.length < len) return false;
  return crc16(buf, len - 2) === buf.readUInt16LE(len - 2);
}

// ---------------------------------------------------------------- drive model
const s16 = (v) => ((v & 0xFFFF) << 16) >> 16;
const u16 = (v) => v & 0xFFFF;

const drive = {
  // RxPDO / writable objects
  controlWord: 0,        // obj 68  (0x6040)  U16 RW  reg 3000
  targetVelocity: 0,     // obj 210 (0x60FF)  I16 RW  reg 3001  0.1 Hz
  torqueLimit: 0,        // obj 209           I16 RW  reg 3002 / 2002  0.1 A
  watchdog: 0,           // no index          U16 RW  reg 3003  ms
  // internal state (DS402)
  state: 'SWITCH_ON_DISABLED',
  errorCode: 0,          // obj 70 (0x603F)
  actualSpeed: 0,        // obj 168, 0.1 Hz (kept as float internally)
  accelerating: false,
  // constant / measured values
  tempPowerStage: 170,   // obj 41   0.1 degC (17.0 degC, as in manual example 6.2)
  tempMotor: 235,        // obj 63   0.1 degC
  dcVoltage: 5650,       // obj 33   0.1 V
  hardwareId: 0x00002310,        // obj 2
  hardwareVersion: 0x00020010,   // obj 5  (2.16)
  softwareId: 0x00000D4B,        // obj 16
  softwareVersion: 0x00040012,   // obj 17 (4.18)
  maxIq: 200,            // obj 171  0.1 A  (20.0 A)
  maxSpeed: 10000,       // obj 120  (1000.0 Hz; 0x3FFF = speed scaling)
  speedScaling: 98298000,  // obj 177  0.001 rpm -> 10000/0x3FFF*98298 rpm = 60000 rpm = 1000 Hz
  currentScaling: 40000,   // obj 182  0.001 A (40.000 A)
};
let lastWatchdogWrite = Date.now();
const ERR_HEARTBEAT = 0x8130; // CiA 301/402 "life guard / heartbeat error"

const ACCEL = 2000;       // 0.1 Hz per second (200 Hz/s)
const DECEL = 2000;
const QS_DECEL = 10000;   // quick stop: 1000 Hz/s

function statusWord() {
  const REMOTE = 0x0200, VOLT = 0x0010;
  let sw;
  switch (drive.state) {
    case 'SWITCH_ON_DISABLED': sw = 0x0040 | VOLT; break;
    case 'READY_TO_SWITCH_ON': sw = 0x0021 | VOLT; break;
    case 'SWITCHED_ON': sw = 0x0023 | VOLT; break;
    case 'OPERATION_ENABLED': sw = 0x0027 | VOLT; break;
    case 'QUICK_STOP_ACTIVE': sw = 0x0007 | VOLT; break;
    case 'FAULT': sw = 0x0008 | VOLT; break;
    default: sw = 0;
  }
  sw |= REMOTE;
  const spd = Math.round(drive.actualSpeed);
  if (drive.state === 'OPERATION_ENABLED') {
    if (Math.abs(spd - effectiveTarget()) <= 10) sw |= 0x0400;
    if (effectiveTorqueLimit() < drive.torqueLimit) sw |= 0x0800; // internal limit active
  } else if (spd === 0) {
    sw |= 0x0400;
  }
  return sw;
}
function effectiveTorqueLimit() { return Math.max(0, Math.min(drive.torqueLimit, drive.maxIq)); }
function effectiveTarget() {
  if (drive.controlWord & 0x0100) return 0; // halt
  return Math.max(-drive.maxSpeed, Math.min(drive.maxSpeed, drive.targetVelocity));
}

function applyControlWord(newCw) {
  const old = drive.controlWord;
  drive.controlWord = newCw;
  if (drive.state === 'FAULT') {
    if (!(old & 0x80) && (newCw & 0x80)) { // fault reset: rising edge of bit 7
      drive.state = 'SWITCH_ON_DISABLED';
      drive.errorCode = 0;
      lastWatchdogWrite = Date.now();
    }
    return;
  }
  if (newCw & 0x80) return; // fault reset bit set, not in fault: no transition
  const b = newCw & 0x0F;
  const disableVoltage = (b & 0x02) === 0;
  const quickStop = (b & 0x06) === 0x02;
  const shutdown = (b & 0x07) === 0x06;
  const switchOn = (b & 0x0F) === 0x07;
  const enableOp = (b & 0x0F) === 0x0F;
  const st = drive.state;
  if (disableVoltage) { drive.state = 'SWITCH_ON_DISABLED'; return; }
  if (quickStop) {
    if (st === 'OPERATION_ENABLED') drive.state = 'QUICK_STOP_ACTIVE';
    else if (st === 'READY_TO_SWITCH_ON' || st === 'SWITCHED_ON') drive.state = 'SWITCH_ON_DISABLED';
    return;
  }
  if (shutdown) {
    if (st === 'SWITCH_ON_DISABLED' || st === 'SWITCHED_ON' || st === 'OPERATION_ENABLED') drive.state = 'READY_TO_SWITCH_ON';
    // quick stop active + shutdown: stays (bit 2 set again has no transition in DS402 except via enable)
    return;
  }
  if (switchOn) {
    if (st === 'READY_TO_SWITCH_ON' || st === 'OPERATION_ENABLED') drive.state = 'SWITCHED_ON';
    return;
  }
  if (enableOp) {
    if (st === 'READY_TO_SWITCH_ON' || st === 'SWITCHED_ON' || st === 'QUICK_STOP_ACTIVE') drive.state = 'OPERATION_ENABLED';
  }
}

function enterFault(code) {
  if (drive.state === 'FAULT') return;
  drive.state = 'FAULT';
  drive.errorCode = code;
}

const TICK = 20;
let lastTick = Date.now();
const ticker = setInterval(() => {
  const now = Date.now();
  const dt = Math.min(0.2, (now - lastTick) / 1000);
  lastTick = now;
  if (drive.watchdog !== 0 && now - lastWatchdogWrite > drive.watchdog) {
    enterFault(ERR_HEARTBEAT);
    lastWatchdogWrite = now;
  }
  let v = drive.actualSpeed;
  drive.accelerating = false;
  if (drive.state === 'OPERATION_ENABLED') {
    const tgt = effectiveTarget();
    if (effectiveTorqueLimit() > 0) {
      const step = ACCEL * dt;
      if (Math.abs(tgt - v) <= step) v = tgt;
      else { v += Math.sign(tgt - v) * step; drive.accelerating = true; }
    } else {
      v = toward0(v, 200 * dt); // no torque allowed: motor coasts down
    }
  } else if (drive.state === 'QUICK_STOP_ACTIVE') {
    v = toward0(v, QS_DECEL * dt);
  } else {
    v = toward0(v, DECEL * dt);
  }
  drive.actualSpeed = v;
}, TICK);
function toward0(v, step) { return Math.abs(v) <= step ? 0 : v - Math.sign(v) * step; }

function measured() {
  const spd = Math.round(drive.actualSpeed);
  const enabled = drive.state === 'OPERATION_ENABLED' || drive.state === 'QUICK_STOP_ACTIVE';
  let cur = 0, volt = 0, pwr = 0;
  if (enabled) {
    const lim = effectiveTorqueLimit();
    cur = drive.accelerating ? lim : Math.min(lim, 8 + Math.round(Math.abs(spd) / 100));
    if (lim === 0) cur = 0;
    volt = Math.min(4000, 50 + Math.round(Math.abs(spd) * 0.4));
    pwr = Math.round(Math.abs(spd) * cur / 10000);
  }
  return { spd, cur, volt, pwr };
}

// ---------------------------------------------------------------- register map
// TxPDO (input image) 2000..2023, RxPDO (holding image) 3000..3003.
// FC03 and FC04 are treated identically (manual 3.1): both read either image.
function readRegister(addr) {
  const m = measured();
  switch (addr) {
    case 2000: return statusWord();
    case 2001: return u16(m.spd);
    case 2002: return u16(drive.torqueLimit);
    case 2003: return u16(m.cur);
    case 2004: return u16(m.pwr);
    case 2005: return u16(drive.errorCode);
    case 2006: return u16(drive.tempPowerStage);
    case 2007: return u16(drive.tempMotor);
    case 2008: return u16(m.volt);
    case 2009: return u16(drive.dcVoltage);
    case 2010: return (drive.hardwareId >>> 16) & 0xFFFF;
    case 2011: return drive.hardwareId & 0xFFFF;
    case 2012: return (drive.hardwareVersion >>> 16) & 0xFFFF;
    case 2013: return drive.hardwareVersion & 0xFFFF;
    case 2014: return (drive.softwareId >>> 16) & 0xFFFF;
    case 2015: return drive.softwareId & 0xFFFF;
    case 2016: return (drive.softwareVersion >>> 16) & 0xFFFF;
    case 2017: return drive.softwareVersion & 0xFFFF;
    case 2018: return u16(drive.maxIq);
    case 2019: return u16(drive.maxSpeed);
    case 2020: return (drive.speedScaling >>> 16) & 0xFFFF;
    case 2021: return drive.speedScaling & 0xFFFF;
    case 2022: return (drive.currentScaling >>> 16) & 0xFFFF;
    case 2023: return drive.currentScaling & 0xFFFF;
    case 3000: return drive.controlWord;
    case 3001: return u16(drive.targetVelocity);
    case 3002: return u16(drive.torqueLimit);
    case 3003: return drive.watchdog;
  }
  return undefined;
}
const isReadable = (a) => (a >= 2000 && a <= 2023) || (a >= 3000 && a <= 3003);
const isWritable = (a) => a >= 3000 && a <= 3003;
function writeRegister(addr, val) {
  switch (addr) {
    case 3000: applyControlWord(val & 0xFFFF); break;
    case 3001: drive.targetVelocity = s16(val); break;
    case 3002: drive.torqueLimit = s16(val); break;
    case 3003: drive.watchdog = val & 0xFFFF; lastWatchdogWrite = Date.now(); break;
  }
}
// Apply a block of writes: setpoints first, control word last, so that
// "enable + setpoint" in one telegram acts on the new setpoint.
function writeBlock(start, values) {
  const order = values.map((v, i) => [start + i, v]).sort((a, b) => (a[0] === 3000) - (b[0] === 3000));
  for (const [a, v] of order) writeRegister(a, v);
}

// ---------------------------------------------------------------- object dictionary (FC 43)
// index -> { size (bytes), signed, access, get, set }
const OD = {
  2: { size: 4, access: 'ro', get: () => drive.hardwareId },
  5: { size: 4, access: 'ro', get: () => drive.hardwareVersion },
  16: { size: 4, access: 'ro', get: () => drive.softwareId },
  17: { size: 4, access: 'ro', get: () => drive.softwareVersion },
  33: { size: 2, access: 'ro', get: () => drive.dcVoltage },
  41: { size: 2, access: 'ro', get: () => drive.tempPowerStage },
  63: { size: 2, access: 'ro', get: () => drive.tempMotor },
  67: { size: 2, access: 'ro', get: () => statusWord() },
  68: { size: 2, access: 'rw', get: () => drive.controlWord, set: (v) => applyControlWord(v & 0xFFFF) },
  70: { size: 2, access: 'ro', get: () => drive.errorCode },
  120: { size: 2, access: 'ro', get: () => drive.maxSpeed },
  168: { size: 2, access: 'ro', get: () => measured().spd },
  171: { size: 2, access: 'ro', get: () => drive.maxIq },
  177: { size: 4, access: 'ro', get: () => drive.speedScaling },
  182: { size: 4, access: 'ro', get: () => drive.currentScaling },
  209: { size: 2, access: 'rw', get: () => drive.torqueLimit, set: (v) => { drive.torqueLimit = s16(v); } },
  210: { size: 2, access: 'rw', get: () => drive.targetVelocity, set: (v) => { drive.targetVelocity = s16(v); } },
  390: { size: 2, access: 'ro', get: () => measured().pwr },
  431: { size: 2, access: 'ro', get: () => measured().cur },
  434: { size: 2, access: 'ro', get: () => measured().volt },
};

const SDO = {
  CMD_UNKNOWN: 0xFFFF0003,
  WRITE_RO: 0xFFFF000A,
  NO_OBJECT: 0xFFFF000B,
  LEN_WRONG: 0xFFFF0011,
  LEN_HIGH: 0xFFFF0012,
  LEN_LOW: 0xFFFF0013,
  NO_SUBINDEX: 0xFFFF0014,
};

// ---------------------------------------------------------------- diagnostics (FC 08)
const diag = { bus_message: 0, bus_comm_error: 0, bus_exception_error: 0, slave_message: 0, slave_no_response: 0 };

// ---------------------------------------------------------------- library glue
// One jsmodbus ModbusRTUServer over a pseudo socket. Register buffers are
// passed as null so the library hands every FC 03/04/06/16 request to our
// event handlers (its documented "no buffer -> emit event" path).
class FrameSocket extends EventEmitter {
  constructor() { super(); this.sink = null; }
  write(buf, cb) { if (this.sink) this.sink(buf); if (cb) cb(); return true; }
}
let libSocket = null;
let lib = null;
function makeLib() {
  libSocket = new FrameSocket();
  lib = new ModbusRTUServer(libSocket, { holding: null, input: null, coils: null, discrete: null });
  attachHandlers(lib);
}

function libReply(request, cb, body) {
  cb(ModbusRTUResponse.fromRequest(request, body).createPayload());
}
function libException(request, cb, code) {
  libReply(request, cb, new R.ExceptionResponseBody(request.body.fc, code));
}
function readCheck(start, count) {
  if (count < 1 || count > 48) return 3;
  for (let a = start; a < start + count; a++) if (!isReadable(a)) return 2;
  return 0;
}
function readValues(start, count) {
  const v = [];
  for (let a = start; a < start + count; a++) v.push(readRegister(a));
  return v;
}
function attachHandlers(lib) {
lib.on('readHoldingRegisters', (request, cb) => {
  const { start, count } = request.body;
  const e = readCheck(start, count);
  if (e) return libException(request, cb, e);
  libReply(request, cb, new R.ReadHoldingRegistersResponseBody(count * 2, readValues(start, count)));
});
lib.on('readInputRegisters', (request, cb) => {
  const { start, count } = request.body;
  const e = readCheck(start, count);
  if (e) return libException(request, cb, e);
  libReply(request, cb, new R.ReadInputRegistersResponseBody(count * 2, readValues(start, count)));
});
lib.on('writeSingleRegister', (request, cb) => {
  const { address, value } = request.body;
  if (!isWritable(address)) return libException(request, cb, 2);
  writeRegister(address, value);
  libReply(request, cb, R.WriteSingleRegisterResponseBody.fromRequest(request.body));
});
lib.on('writeMultipleRegisters', (request, cb) => {
  // quantity / byte count already validated by the front end (library derives quantity from byte count)
  const { address, valuesAsArray } = request.body;
  for (let a = address; a < address + valuesAsArray.length; a++) if (!isWritable(a)) return libException(request, cb, 2);
  writeBlock(address, valuesAsArray);
  libReply(request, cb, R.WriteMultipleRegistersResponseBody.fromRequest(request.body));
});
}
makeLib();

// Build an RTU frame for our own PDUs (same framing path as the library: address + PDU + CRC).
function rtuFrame(addr, pdu) {
  const body = { byteCount: pdu.length, createPayload: () => pdu };
  return new ModbusRTUResponse(addr, undefined, body).createPayload();
}
function exceptionPdu(fc, code) { return Buffer.from([fc | 0x80, code]); }

// ---------------------------------------------------------------- request processing
// frame: complete RTU frame with valid CRC. Returns response frame Buffer or null.
function processFrame(frame) {
  diag.bus_message++;
  const addr = frame[0];
  if (addr !== UNIT && addr !== 0) return null;
  diag.slave_message++;
  const broadcast = addr === 0;
  const pdu = frame.subarray(1, frame.length - 2);
  const fc = pdu[0];
  let resp = null;
  try {
    resp = dispatch(addr, pdu, frame, broadcast);
  } catch (err) {
    process.stderr.write(`internal error: ${err && err.stack}\n`);
    resp = broadcast ? null : exceptionPdu(fc, 0x04);
  }
  if (broadcast || resp === null) { diag.slave_no_response++; return null; }
  if (resp[0] & 0x80) diag.bus_exception_error++;
  return rtuFrame(addr, resp);
}

function viaLibrary(frame) {
  let out = null;
  libSocket.sink = (buf) => { out = buf; };
  try { libSocket.emit('data', frame); } finally { libSocket.sink = null; }
  if (!out) {
    // the library kept the bytes in its stream buffer without answering; start it afresh
    makeLib();
    return exceptionPdu(frame[1], 0x04);
  }
  const pdu = Buffer.from(out.subarray(1, out.length - 2));
  return pdu;
}

function dispatch(addr, pdu, frame, broadcast) {
  const fc = pdu[0];
  const n = pdu.length;
  switch (fc) {
    case 0x03: case 0x04: {
      if (broadcast) return null;
      if (n !== 5) return exceptionPdu(fc, 0x03);
      const cnt = pdu.readUInt16BE(3);
      if (cnt < 1 || cnt > 48) return exceptionPdu(fc, 0x03); // never hand the library a count it throws on
      return viaLibrary(frame);
    }
    case 0x06:
      if (n !== 5) return broadcast ? null : exceptionPdu(fc, 0x03);
      return viaLibrary(frame);
    case 0x10: {
      if (n < 6) return broadcast ? null : exceptionPdu(fc, 0x03);
      const qty = pdu.readUInt16BE(3), bc = pdu[5];
      if (qty < 1 || qty > 48 || bc !== qty * 2 || n !== 6 + bc) return broadcast ? null : exceptionPdu(fc, 0x03);
      return viaLibrary(frame);
    }
    case 0x08: return broadcast ? null : fc08(pdu);
    case 0x17: return broadcast ? null : fc23(pdu);
    case 0x2B: return broadcast ? null : fc43(addr, pdu);
    default:
      return broadcast ? null : exceptionPdu(fc & 0x7F, 0x01);
  }
}

function fc08(pdu) {
  if (pdu.length < 3) return exceptionPdu(0x08, 0x03);
  const sub = pdu.readUInt16BE(1);
  const supported = [0x00, 0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F];
  if (!supported.includes(sub)) return exceptionPdu(0x08, 0x01);
  if (pdu.length !== 5) return exceptionPdu(0x08, 0x03);
  const data = pdu.readUInt16BE(3);
  const out = Buffer.from(pdu);
  switch (sub) {
    case 0x00: break; // echo
    case 0x0A:
      for (const k of Object.keys(diag)) diag[k] = 0;
      break;
    case 0x0B: out.writeUInt16BE(diag.bus_message & 0xFFFF, 3); break;
    case 0x0C: out.writeUInt16BE(diag.bus_comm_error & 0xFFFF, 3); break;
    case 0x0D: out.writeUInt16BE(diag.bus_exception_error & 0xFFFF, 3); break;
    case 0x0E: out.writeUInt16BE(diag.slave_message & 0xFFFF, 3); break;
    case 0x0F: out.writeUInt16BE(diag.slave_no_response & 0xFFFF, 3); break;
  }
  void data;
  return out;
}

function fc23(pdu) {
  if (pdu.length < 10) return exceptionPdu(0x17, 0x03);
  const rStart = pdu.readUInt16BE(1), rQty = pdu.readUInt16BE(3);
  const wStart = pdu.readUInt16BE(5), wQty = pdu.readUInt16BE(7), bc = pdu[9];
  if (rQty < 1 || rQty > 48 || wQty < 1 || wQty > 48 || bc !== wQty * 2 || pdu.length !== 10 + bc) {
    return exceptionPdu(0x17, 0x03);
  }
  for (let a = wStart; a < wStart + wQty; a++) if (!isWritable(a)) return exceptionPdu(0x17, 0x02);
  for (let a = rStart; a < rStart + rQty; a++) if (!isReadable(a)) return exceptionPdu(0x17, 0x02);
  const vals = [];
  for (let i = 0; i < wQty; i++) vals.push(pdu.readUInt16BE(10 + 2 * i));
  writeBlock(wStart, vals); // write is performed before the read (Modbus spec)
  const out = Buffer.alloc(2 + rQty * 2);
  out[0] = 0x17; out[1] = rQty * 2;
  readValues(rStart, rQty).forEach((v, i) => out.writeUInt16BE(v, 2 + 2 * i));
  return out;
}

// FC 43 / MEI 0x0D. Two header layouts are accepted (see DECISIONS.md):
//  table layout:   2B 0D ctrl res node idxH idxL sub offH offL cntH cntL data...
//  example layout: 2B 0D ctrl     node idxH idxL sub offH offL cntH cntL data...
function mei0dLayout(pdu) {
  // returns header length (12 table / 11 example) whose length field matches the PDU, or 0
  const fits = (hl) => {
    if (pdu.length < hl) return false;
    const ctrl = pdu[2];
    const cnt = pdu.readUInt16BE(hl - 2);
    const dataLen = (ctrl & 0x80) ? cnt : 0;
    return pdu.length === hl + dataLen;
  };
  if (fits(12)) return 12;
  if (fits(11)) return 11;
  return 0;
}
function fc43(addr, pdu) {
  if (pdu.length < 2) return exceptionPdu(0x2B, 0x03);
  const mei = pdu[1];
  if (mei !== 0x0D) return exceptionPdu(0x2B, 0x01);
  const hl = mei0dLayout(pdu);
  if (!hl) return exceptionPdu(0x2B, 0x03);
  const off = hl - 12; // 0 for table layout, -1 for example layout (no reserved byte)
  const ctrl = pdu[2];
  const reserved = hl === 12 ? pdu[3] : 0;
  const node = pdu[4 + off];
  const index = pdu.readUInt16BE(5 + off);
  const sub = pdu[7 + off];
  const aoff = pdu.readUInt16BE(8 + off);
  const cnt = pdu.readUInt16BE(10 + off);
  const write = (ctrl & 0x80) !== 0;
  if (reserved !== 0 || node !== addr || aoff !== 0 || cnt > 4) return exceptionPdu(0x2B, 0x03);
  const sdoErr = (code) => {
    const b = Buffer.alloc(10);
    b[0] = 0xAB; b[1] = 0xFF; b.writeUInt16BE(6, 2); b[4] = 0x0D; b[5] = 0xCE;
    b.writeUInt32LE(code >>> 0, 6);
    return b;
  };
  if ((ctrl & 0x7F) !== 0) return sdoErr(SDO.CMD_UNKNOWN);
  const obj = OD[index];
  if (!obj) return sdoErr(SDO.NO_OBJECT);
  if (sub !== 0) return sdoErr(SDO.NO_SUBINDEX);
  if (cnt > obj.size) return sdoErr(SDO.LEN_HIGH);
  if (cnt < obj.size) return sdoErr(SDO.LEN_LOW);
  const header = Buffer.from(pdu.subarray(0, hl));
  if (write) {
    if (obj.access !== 'rw') return sdoErr(SDO.WRITE_RO);
    const v = obj.size === 2 ? pdu.readUInt16LE(hl) : pdu.readUInt32LE(hl);
    obj.set(v);
    return Buffer.from(pdu); // echo request incl. written data
  }
  const data = Buffer.alloc(obj.size);
  const v = obj.get();
  if (obj.size === 2) data.writeUInt16LE(v & 0xFFFF, 0); else data.writeUInt32LE(v >>> 0, 0);
  return Buffer.concat([header, data]);
}

// ---------------------------------------------------------------- RTU framing front end
// Frame length of a request, as far as it can be known from the bytes so far.
// Returns array of candidate lengths (may be empty if not yet determinable / unknown FC).
function candidateLengths(buf) {
  if (buf.length < 2) return [];
  const fc = buf[1];
  switch (fc) {
    case 0x01: case 0x02: case 0x03: case 0x04: case 0x05: case 0x06: case 0x08:
      return [8];
    case 0x0F: case 0x10:
      return buf.length >= 7 ? [9 + buf[6]] : [];
    case 0x17:
      return buf.length >= 11 ? [13 + buf[10]] : [];
    case 0x2B: {
      if (buf.length < 4) return [];
      const c = [];
      const ctrl = buf[3];
      if (buf.length >= 13) c.push(1 + 12 + ((ctrl & 0x80) ? buf.readUInt16BE(11) : 0) + 2);
      if (buf.length >= 12) c.push(1 + 11 + ((ctrl & 0x80) ? buf.readUInt16BE(10) : 0) + 2);
      return c;
    }
    case 0x07: case 0x0B: case 0x0C: case 0x11:
      return [4];
  }
  return [];
}

class RtuLink {
  constructor(send, gapMs) {
    this.send = send;
    this.gapMs = gapMs;
    this.buf = Buffer.alloc(0);
    this.timer = null;
  }
  onData(chunk) {
    this.buf = this.buf.length ? Buffer.concat([this.buf, chunk]) : Buffer.from(chunk);
    if (this.timer) { clearTimeout(this.timer); this.timer = null; }
    let guard = 0;
    while (this.buf.length >= 4 && guard++ < 64) {
      const lens = candidateLengths(this.buf);
      const len = lens.find((l) => l <= 256 && this.buf.length >= l && crcOk(this.buf, l));
      if (!len) break;
      const frame = this.buf.subarray(0, len);
      this.buf = this.buf.subarray(len);
      this.handle(Buffer.from(frame));
    }
    if (this.buf.length > 512) { diag.bus_comm_error++; this.buf = Buffer.alloc(0); }
    if (this.buf.length) this.timer = setTimeout(() => this.onSilence(), this.gapMs);
  }
  onSilence() {
    this.timer = null;
    const b = this.buf;
    this.buf = Buffer.alloc(0);
    if (b.length >= 4 && b.length <= 256 && crcOk(b, b.length)) this.handle(b); // well-formed frame, unexpected length
    else if (b.length > 0) diag.bus_comm_error++;
  }
  handle(frame) {
    let out = null;
    try { out = processFrame(frame); } catch (e) { process.stderr.write(`error: ${e && e.stack}\n`); }
    if (out) this.send(out);
  }
  close() { if (this.timer) clearTimeout(this.timer); this.timer = null; }
}

// ---------------------------------------------------------------- state dump
function hex4(n) { return '0x' + n.toString(16).toUpperCase().padStart(4, '0'); }
function dumpState() {
  const regs = {};
  for (let a = 2000; a <= 2023; a++) regs[String(a)] = readRegister(a);
  const hold = {};
  for (let a = 3000; a <= 3003; a++) hold[String(a)] = readRegister(a);
  const od = {};
  for (const k of Object.keys(OD).map(Number).sort((x, y) => x - y)) {
    const o = OD[k];
    let v = o.get();
    v = o.size === 2 ? (v & 0xFFFF) : (v >>> 0);
    od[`${k}:0`] = { index: k, index_hex: hex4(k), subindex: 0, access: o.access, size: o.size, value: v };
  }
  return {
    device: 'SIEB & MEYER SD2x (simulated)',
    settings: { slave_address: UNIT, transport: opts.serial ? 'serial' : 'tcp', baud: opts.baud, parity: opts.parity },
    drive_state: drive.state,
    input_registers: regs,
    holding_registers: hold,
    objects: od,
    diagnostic_counters: { ...diag },
  };
}
function writeState() {
  if (!opts.state) return;
  try {
    const tmp = opts.state + '.tmp';
    fs.writeFileSync(tmp, JSON.stringify(dumpState(), null, 2) + '\n');
    fs.renameSync(tmp, opts.state);
  } catch (e) { process.stderr.write(`state write failed: ${e.message}\n`); }
}

// ---------------------------------------------------------------- transports
let closers = [];
let exiting = false;
function shutdown(code) {
  if (exiting) return;
  exiting = true;
  writeState();
  clearInterval(ticker);
  for (const c of closers) { try { c(); } catch (_) { /* ignore */ } }
  process.exit(code);
}
process.on('SIGTERM', () => shutdown(0));
process.on('SIGINT', () => shutdown(0));
process.on('SIGHUP', () => shutdown(0));
process.on('SIGUSR1', () => writeState());
process.on('uncaughtException', (e) => { process.stderr.write(`uncaught: ${e && e.stack}\n`); });
process.on('unhandledRejection', (e) => { process.stderr.write(`unhandled: ${e && e.stack}\n`); });

function charTimeMs() {
  const bits = 1 + 8 + (opts.parity === 'none' ? 0 : 1) + 1;
  return (bits * 1000) / opts.baud;
}

if (opts.listen) {
  const m = /^(.*):(\d+)$/.exec(opts.listen);
  if (!m) usage('--listen needs HOST:PORT');
  const host = m[1], port = parseInt(m[2], 10);
  const sockets = new Set();
  const srv = net.createServer((sock) => {
    sockets.add(sock);
    sock.setNoDelay(true);
    const link = new RtuLink((b) => { if (!sock.destroyed) sock.write(b); }, 50);
    sock.on('data', (d) => link.onData(d));
    sock.on('error', () => { /* ignore */ });
    sock.on('close', () => { link.close(); sockets.delete(sock); });
  });
  srv.on('error', (e) => { process.stderr.write(`listen error: ${e.message}\n`); process.exit(1); });
  srv.listen(port, host, () => {
    process.stdout.write(`listening tcp ${host}:${srv.address().port}\n`);
  });
  closers.push(() => { srv.close(); for (const s of sockets) s.destroy(); });
} else {
  const { SerialPort } = require('serialport');
  const gap = Math.max(15, Math.ceil(charTimeMs() * 3.5));
  let port = null;
  const open = (parity, fallback) => {
    const p = new SerialPort({ path: opts.serial, baudRate: opts.baud, dataBits: 8, stopBits: 1, parity, autoOpen: false });
    p.open((err) => {
      if (err) {
        if (fallback && parity !== 'none') {
          process.stderr.write(`serial: cannot open with parity ${parity} (${err.message}); falling back to parity none\n`);
          return open('none', false);
        }
        process.stderr.write(`serial open failed: ${err.message}\n`);
        process.exit(1);
      }
      port = p;
      const link = new RtuLink((b) => { p.write(b); }, gap);
      p.on('data', (d) => link.onData(d));
      p.on('error', (e) => process.stderr.write(`serial error: ${e.message}\n`));
      p.on('close', () => link.close());
      process.stdout.write(`listening serial ${opts.serial}\n`);
    });
  };
  open(opts.parity, true);
  closers.push(() => { if (port && port.isOpen) port.close(); });
}

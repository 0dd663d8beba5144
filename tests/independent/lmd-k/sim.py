#!/usr/bin/env python3
"""Lexium MDrive (LMD) Ethernet -- Modbus/TCP server simulator (team lmd-k).

Bench unit: logic (aux) supply only, +V motor supply absent -> ER=120, EF=1, AF=32,
VT reports "24,0".  See DECISIONS.md.  Standard library only.
"""
import argparse
import asyncio
import copy
import json
import os
import signal
import sys

# ---------------------------------------------------------------------------
# Register map (manual section 5).  Low word at the lower address (manual
# examples lines 938-956 and 1009-1035), big-endian bytes inside a register.
# (mnemonic, address, words, access, min, max, default, signed, kind)
#   access: rw / ro / wo ;  kind: None, 'motion', 'action'
# ---------------------------------------------------------------------------
I32MIN, I32MAX = -2147483648, 2147483647
PARAMS = [
    ("A", 0x0000, 2, "rw", 91, 1525878997, 1000000, False, None),
    ("BY", 0x0004, 1, "ro", 0, 1, 0, False, None),
    ("C1", 0x0005, 2, "rw", I32MIN, I32MAX, 0, True, None),
    ("C2", 0x0007, 2, "rw", I32MIN, I32MAX, 0, True, None),
    ("CE", 0x0009, 1, "rw", 0, 1, 1, False, None),
    ("CW", 0x000E, 1, "rw", 0, 255, 10, False, None),
    ("D1", 0x000F, 1, "rw", 0, 255, 0, False, None),
    ("D2", 0x0010, 1, "rw", 0, 255, 0, False, None),
    ("D3", 0x0011, 1, "rw", 0, 255, 0, False, None),
    ("D4", 0x0012, 1, "rw", 0, 255, 0, False, None),
    ("D5", 0x0013, 1, "rw", 0, 255, 0, False, None),
    ("D", 0x0018, 2, "rw", 91, 1525878997, 1000000, False, None),
    ("DB", 0x001A, 1, "rw", 0, 65000, 10, False, None),
    ("DC", 0x001B, 1, "wo", 1, 4, None, False, "action"),
    ("DE", 0x001C, 1, "rw", 0, 1, 1, False, None),
    ("EE", 0x001E, 1, "rw", 0, 1, 0, False, None),
    ("EF", 0x001F, 1, "ro", 0, 1, 0, False, None),
    ("ER", 0x0021, 1, "rw", 0, 0, 0, False, None),
    ("FC", 0x0024, 1, "rw", 0, 9, 0, False, None),
    ("HC", 0x0029, 1, "rw", 0, 100, 5, False, None),
    ("HI", 0x002A, 1, "wo", 1, 4, None, False, "motion"),
    ("HM", 0x002B, 1, "wo", 1, 4, None, False, "motion"),
    ("HT", 0x002C, 1, "rw", 0, 65535, 500, False, None),
    ("I1", 0x002D, 1, "ro", 0, 1, 0, False, None),
    ("I2", 0x002E, 1, "ro", 0, 1, 0, False, None),
    ("I3", 0x002F, 1, "ro", 0, 1, 0, False, None),
    ("I4", 0x0030, 1, "ro", 0, 1, 0, False, None),
    ("I5", 0x0031, 1, "ro", 0, 1023, 0, False, None),
    ("I6", 0x0032, 1, "ro", 0, 1, 0, False, None),
    ("IC", 0x0037, 1, "wo", 1, 4, None, False, "action"),
    ("IN", 0x003B, 1, "ro", 0, 15, 0, False, None),
    ("IP", 0x003C, 1, "wo", 0, 65535, None, False, "action"),
    ("JE", 0x003F, 1, "rw", 0, 1, 0, False, None),
    ("LM", 0x0042, 1, "rw", 1, 6, 1, False, None),
    ("MA", 0x0043, 2, "wo", I32MIN, I32MAX, None, True, "motion"),
    ("MP", 0x0045, 1, "ro", 0, 1, 0, False, None),
    ("MR", 0x0046, 2, "wo", I32MIN, I32MAX, None, True, "motion"),
    ("MS", 0x0048, 1, "rw", 1, 256, 256, False, None),
    ("MT", 0x0049, 1, "rw", 0, 65000, 0, False, None),
    ("MV", 0x004A, 1, "ro", 0, 1, 0, False, None),
    ("O1", 0x004B, 1, "rw", 0, 1, 0, False, None),
    ("O2", 0x004C, 1, "rw", 0, 1, 0, False, None),
    ("O3", 0x004D, 1, "rw", 0, 1, 0, False, None),
    ("OF", 0x004E, 1, "ro", 0, 1, 0, False, None),
    ("OT", 0x0056, 1, "rw", 0, 15, 0, False, None),
    ("P", 0x0057, 2, "rw", I32MIN, I32MAX, 0, True, None),
    ("PC", 0x0059, 2, "ro", I32MIN, I32MAX, 0, True, None),
    ("PM", 0x005C, 1, "rw", 0, 1, 0, False, None),
    ("R1", 0x005F, 2, "rw", I32MIN, I32MAX, 0, True, None),
    ("R2", 0x0061, 2, "rw", I32MIN, I32MAX, 0, True, None),
    ("R3", 0x0063, 2, "rw", I32MIN, I32MAX, 0, True, None),
    ("R4", 0x0065, 2, "rw", I32MIN, I32MAX, 0, True, None),
    ("RC", 0x0067, 1, "rw", 1, 100, 25, False, None),
    ("S", 0x0076, 1, "wo", 0, 65535, None, False, "action"),
    ("SF", 0x0077, 1, "rw", 0, 65000, 15, False, None),
    ("SL", 0x0078, 2, "wo", -5000000, 5000000, None, True, "motion"),
    ("SM", 0x007A, 1, "rw", 0, 1, 0, False, None),
    ("ST", 0x007B, 1, "ro", 0, 1, 0, False, None),
    ("TE", 0x007D, 1, "rw", 0, 63, 0, False, None),
    ("V", 0x0085, 2, "ro", I32MIN, I32MAX, 0, True, None),
    ("VC", 0x0088, 1, "ro", 0, 1, 0, False, None),
    ("VI", 0x0089, 2, "rw", 1, 2559999, 1000, False, None),
    ("VM", 0x008B, 2, "rw", 2, 2560000, 768000, False, None),
    ("WT", 0x008D, 1, "rw", 0, 84, 80, False, None),
    ("AS", 0x008E, 1, "rw", 0, 3, 2, False, None),
    ("AF", 0x008F, 1, "ro", 0, 255, 0, False, None),
    ("CB", 0x0091, 1, "rw", 0, 3, 1, False, None),
    ("CF", 0x0093, 1, "wo", 0, 65535, None, False, "action"),
    ("LD", 0x0095, 2, "rw", 0, I32MAX, 102400, False, None),
    ("LG", 0x0097, 2, "rw", 0, I32MAX, 102400, False, None),
    ("LL", 0x0099, 2, "ro", -I32MAX, I32MAX, 0, True, None),
    ("LR", 0x009B, 1, "ro", 0, 1, 0, False, None),
    ("LT", 0x009C, 2, "rw", 2, 65535, 2000, False, None),
    ("MF", 0x009E, 2, "rw", 306, 2560000, 768000, False, None),
    ("MU", 0x00A0, 1, "rw", 0, 2, 0, False, None),
    ("SC", 0x00A1, 1, "wo", 0, 65535, None, False, "motion"),
    ("TS", 0x00A3, 2, "rw", 0, 255, 0, False, None),
    ("TD", 0x00A5, 1, "rw", 0, 1, 1, False, None),
    ("TQ", 0x00A6, 1, "rw", 1, 100, 25, False, None),
    ("VF", 0x00A7, 1, "rw", 0, 1000, 0, False, None),
] + [("V%d" % (i + 1), 0x00A8 + 2 * i, 2, "rw", I32MIN, I32MAX, 0, True, None) for i in range(8)]

P = {p[0]: dict(mn=p[0], addr=p[1], words=p[2], acc=p[3], lo=p[4], hi=p[5],
                default=p[6], signed=p[7], kind=p[8]) for p in PARAMS}
REGMAP = {}  # address -> (mnemonic, word index 0=low 1=high)
for _p in P.values():
    for _i in range(_p["words"]):
        REGMAP[_p["addr"] + _i] = (_p["mn"], _i)

MS_ALLOWED = {1, 2, 4, 5, 8, 10, 16, 25, 32, 50, 64, 100, 125, 128, 200, 250, 256, 180, 108, 127}
# parameters restored by IP (initialize parameters) and saved by S
_NOT_CONFIG = {"C1", "C2", "P", "R1", "R2", "R3", "R4", "ER", "O1", "O2", "O3", "OT",
               "V1", "V2", "V3", "V4", "V5", "V6", "V7", "V8"}
CONFIG_PARAMS = sorted(m for m, p in P.items() if p["acc"] == "rw" and m not in _NOT_CONFIG)

ERR_UNDERVOLTAGE = 120      # our firmware's ER code: +V supply under-voltage
DEV_ID = {
    0: b"IMS USA",
    1: b"LMDCE421",
    2: b"4.0.0.0",
    3: b"https://novantaims.com/",
    4: b"LMD Ethernet",
    5: b"LMD2112A0457",
    6: b"LMDCM 6.024, Hw: 1.0",
}
IN_FUNCS = {0, 1, 2, 3, 5, 7, 8, 11, 12}
OUT_FUNCS = {16, 17, 18, 20, 21, 23, 24, 25, 28, 29}
UG_KEY = "2956102"


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


def default_mfg():
    return {
        "AO": 0,
        "inputs": {str(n): {"function": 0, "active": 0, "sink": 0} for n in (1, 2, 3, 4)},
        "analog": {"mode": 9, "range": 0},
        "outputs": {str(n): {"function": 16, "active": 0} for n in (1, 2, 3)},
        "MU_leadlag": 0,
        "RD": 0, "AJ": 128, "AT": 0, "BE": 0, "BL": 0, "BM": 0, "DJ": 128, "DT": 0,
        "FS": 0, "FL": 0,
        "LS": {"0": {"position": 0, "enable": 0}, "1": {"position": 0, "enable": 0}},
        "TR": [0, 0, 0],
    }


class Drive:
    def __init__(self):
        self.vals = {m: p["default"] for m, p in P.items() if p["acc"] != "wo"}
        self.mfg = default_mfg()
        self.outputs = [0, 0, 0, 0]      # logic state of outputs 1-4
        self.inputs = [0, 0, 0, 0]       # logic state of inputs 1-4 (nothing wired)
        # supply / error state (the bench condition)
        self.aux_voltage = 24
        self.plus_v_voltage = 0
        self.temp_bridge = 27
        self.temp_micro = 31
        self.program = {"stored": False, "running": False, "paused": False}
        self.nvm = self._config_snapshot()
        self.diag = {"requests": 0, "exceptions": 0, "bad_frames": 0, "connections": 0}
        self._monitor()

    # -- supply monitor: re-latch the error while its cause exists -------------
    def cause_present(self):
        return self.plus_v_voltage < 12

    def _monitor(self):
        if self.cause_present():
            self.vals["ER"] = ERR_UNDERVOLTAGE
            self.vals["EF"] = 1
            self.vals["AF"] = 32
        else:
            self.vals["EF"] = 1 if self.vals["ER"] else 0

    def _config_snapshot(self):
        return {"registers": {m: self.vals[m] for m in CONFIG_PARAMS},
                "mfg": copy.deepcopy(self.mfg)}

    # -- register level ---------------------------------------------------------
    def _param_value(self, mn):
        if mn in ("O1", "O2", "O3"):
            return self.outputs[int(mn[1]) - 1]
        if mn == "OT":
            return sum(b << i for i, b in enumerate(self.outputs))
        if mn in ("I1", "I2", "I3", "I4"):
            return self.inputs[int(mn[1]) - 1]
        if mn == "IN":
            return sum(b << i for i, b in enumerate(self.inputs))
        return self.vals[mn]

    def read_regs(self, start, qty):
        out = []
        touched = []
        for a in range(start, start + qty):
            ent = REGMAP.get(a)
            if ent is None:
                raise ModbusError(2)
            mn, idx = ent
            if P[mn]["acc"] == "wo":
                raise ModbusError(2)
        for a in range(start, start + qty):
            mn, idx = REGMAP[a]
            v = self._param_value(mn) & 0xFFFFFFFF
            out.append((v >> (16 * idx)) & 0xFFFF)
            touched.append(mn)
        if "ER" in touched:
            # manual 2085: reading ER clears it; the monitor re-latches at once
            self.vals["ER"] = 0
            self._monitor()
        return out

    def write_regs(self, start, words):
        qty = len(words)
        # address checks: every register writable, 32-bit values written whole
        updates = []
        a = start
        while a < start + qty:
            ent = REGMAP.get(a)
            if ent is None:
                raise ModbusError(2)
            mn, idx = ent
            p = P[mn]
            if p["acc"] == "ro" or idx != 0 or a + p["words"] > start + qty:
                raise ModbusError(2)
            raw = 0
            for i in range(p["words"]):
                raw |= words[a - start + i] << (16 * i)
            if p["signed"] and raw & (1 << (16 * p["words"] - 1)):
                raw -= 1 << (16 * p["words"])
            updates.append((mn, raw))
            a += p["words"]
        # value checks (all before any effect)
        for mn, v in updates:
            self._check_value(mn, v, updates)
        for mn, v in updates:
            self._apply(mn, v)

    def _check_value(self, mn, v, updates):
        p = P[mn]
        if not (p["lo"] <= v <= p["hi"]):
            raise ModbusError(3)
        new = dict(updates)
        if mn == "MS" and v not in MS_ALLOWED:
            raise ModbusError(3)
        if mn == "HT" and v == 1:
            raise ModbusError(3)
        if mn in ("HT", "MT"):
            ht = new.get("HT", self.vals["HT"])
            mt = new.get("MT", self.vals["MT"])
            if ht + mt > 65535:
                raise ModbusError(3)
        if mn in ("VI", "VM"):
            vi = new.get("VI", self.vals["VI"])
            vm = new.get("VM", self.vals["VM"])
            if vi >= vm:
                raise ModbusError(3)
        if mn in ("O1", "O2", "O3"):
            n = int(mn[1])
            if self.mfg["outputs"][str(n)]["function"] != 16 and v != self.outputs[n - 1]:
                raise ModbusError(4)
        if mn == "OT":
            for n in (1, 2, 3):
                if self.mfg["outputs"][str(n)]["function"] != 16 and \
                        ((v >> (n - 1)) & 1) != self.outputs[n - 1]:
                    raise ModbusError(4)

    def _apply(self, mn, v):
        p = P[mn]
        if p["kind"] == "motion":
            self._refuse_motion()
            return
        if mn in ("O1", "O2", "O3"):
            self.outputs[int(mn[1]) - 1] = v
        elif mn == "OT":
            self.outputs = [(v >> i) & 1 for i in range(4)]
        elif mn == "ER":
            self.vals["ER"] = 0
            self._monitor()
        elif mn in ("DC", "IC"):
            r = "R%d" % v
            nv = self.vals[r] + (1 if mn == "IC" else -1)
            if nv > I32MAX:
                nv = I32MIN
            elif nv < I32MIN:
                nv = I32MAX
            self.vals[r] = nv
        elif mn == "IP":
            for m in CONFIG_PARAMS:
                self.vals[m] = P[m]["default"]
            self.mfg = default_mfg()
        elif mn == "S":
            self.nvm = self._config_snapshot()
        elif mn == "CF":
            # clear locked rotor: no locked rotor latched; bridge cannot be
            # re-enabled nor calibrated without +V
            self.vals["LR"] = 0
            self._monitor()
        elif mn == "MU":
            self.vals["MU"] = v
        else:
            self.vals[mn] = v

    def _refuse_motion(self):
        # taken, not acted on: the power stage has no supply
        self._monitor()

    # -- coils / inputs -----------------------------------------------------------
    def write_coil(self, addr, on):
        if addr < 3 and self.mfg["outputs"][str(addr + 1)]["function"] != 16 \
                and on != self.outputs[addr]:
            raise ModbusError(4)
        self.outputs[addr] = on

    # -- manufacturer specific functions (FC65/66) -------------------------------
    def mfg_read(self, name):
        m = self.mfg
        if name == "AO":
            return str(m["AO"])
        if name == "IS":
            parts = []
            for n in ("1", "2", "3", "4"):
                parts.append("%s,%d,%d" % (n, m["inputs"][n]["function"], m["inputs"][n]["active"]))
            parts.append("5,%d,%d" % (m["analog"]["mode"], m["analog"]["range"]))
            return ",".join(parts)
        if name in ("S1", "S2", "S3", "S4"):
            i = m["inputs"][name[1]]
            return "%d,%d,%d" % (i["function"], i["active"], i["sink"])
        if name == "S5":
            return "%d,%d" % (m["analog"]["mode"], m["analog"]["range"])
        if name == "OS":
            return ",".join("%s,%d,%d" % (n, m["outputs"][n]["function"], m["outputs"][n]["active"])
                            for n in ("1", "2", "3"))
        if name == "EL":
            return "1000"
        if name == "IT":
            return "%d,%d" % (self.temp_bridge, self.temp_micro)
        if name == "VT":
            return "%d,%d" % (self.aux_voltage, self.plus_v_voltage)
        if name == "MU":
            return "%d,%d" % (self.vals["MU"], m["MU_leadlag"])
        if name in ("RD", "AJ", "AT", "BE", "BL", "BM", "DJ", "DT", "FS", "FL"):
            return str(m[name])
        if name == "AV":
            return "0"
        if name == "LS":
            return ",".join("%s,%d,%d" % (k, m["LS"][k]["position"], m["LS"][k]["enable"])
                            for k in ("0", "1"))
        if name == "TR":
            return ", ".join(str(x) for x in m["TR"])
        if name in WO_MNEMONICS:
            raise ModbusError(2)
        raise ModbusError(2)

    def mfg_write(self, name, data):
        m = self.mfg
        try:
            text = data.decode("ascii")
        except UnicodeDecodeError:
            raise ModbusError(3)
        text = text.strip(" \r\n\x00")
        if text.startswith("="):
            text = text[1:].strip()

        def ints(n_min, n_max):
            if not text:
                raise ModbusError(3)
            parts = [x.strip() for x in text.split(",")]
            if not (n_min <= len(parts) <= n_max):
                raise ModbusError(3)
            out = []
            for x in parts:
                try:
                    if not x or not all(c.isdigit() for c in x.lstrip("+-")) or x.lstrip("+-") == "":
                        raise ValueError
                    out.append(int(x))
                except ValueError:
                    raise ModbusError(3)
            return out

        def rng(v, lo, hi):
            if not (lo <= v <= hi):
                raise ModbusError(3)

        if name in ("ESC", "CP", "PS", "RS", "E"):
            if text:
                raise ModbusError(3)
            if name == "CP":
                self.program = {"stored": False, "running": False, "paused": False}
            return
        if name == "EX":
            if not text or len(text) > 4:
                raise ModbusError(3)
            # no program stored in this unit: the label cannot exist
            raise ModbusError(3)
        if name == "UG":
            if text != UG_KEY:
                raise ModbusError(3)
            raise ModbusError(4)   # boot loader not reachable from Modbus/TCP
        if name == "HF":
            (v,) = ints(1, 1)
            rng(v, 0, 1)
            self._refuse_motion()
            return
        if name in ("IT", "VT", "AV", "EL"):
            raise ModbusError(2)
        if name == "AO":
            (v,) = ints(1, 1)
            rng(v, 0, 65535)
            m["AO"] = v
            return
        if name == "IS":
            a = ints(3, 3)
            if a[0] in (1, 2, 3, 4):
                if a[1] not in IN_FUNCS:
                    raise ModbusError(3)
                rng(a[2], 0, 1)
                m["inputs"][str(a[0])]["function"] = a[1]
                m["inputs"][str(a[0])]["active"] = a[2]
            elif a[0] == 5:
                if a[1] not in (9, 10):
                    raise ModbusError(3)
                rng(a[2], 0, 1)
                m["analog"] = {"mode": a[1], "range": a[2]}
            else:
                raise ModbusError(3)
            return
        if name in ("S1", "S2", "S3", "S4"):
            a = ints(2, 3)
            if a[0] not in IN_FUNCS:
                raise ModbusError(3)
            rng(a[1], 0, 1)
            if len(a) == 3:
                rng(a[2], 0, 1)
            i = m["inputs"][name[1]]
            i["function"], i["active"] = a[0], a[1]
            if len(a) == 3:
                i["sink"] = a[2]
            return
        if name == "S5":
            a = ints(2, 2)
            if a[0] not in (9, 10):
                raise ModbusError(3)
            rng(a[1], 0, 1)
            m["analog"] = {"mode": a[0], "range": a[1]}
            return
        if name == "OS":
            a = ints(3, 3)
            rng(a[0], 1, 3)
            if a[1] not in OUT_FUNCS or (a[1] == 28 and a[0] != 3):
                raise ModbusError(3)
            rng(a[2], 0, 1)
            m["outputs"][str(a[0])] = {"function": a[1], "active": a[2]}
            return
        if name == "MU":
            a = ints(1, 2)
            rng(a[0], 0, 2)
            if len(a) == 2:
                rng(a[1], 0, 1)
                m["MU_leadlag"] = a[1]
                if a[1] == 1:
                    self.vals["LL"] = 0
            self.vals["MU"] = a[0]
            return
        simple = {"RD": (0, 1), "AT": (0, 1), "DT": (0, 1), "BE": (0, 1), "BM": (0, 1),
                  "FL": (0, 1), "AJ": (1, 999), "DJ": (1, 999), "BL": (0, I32MAX),
                  "FS": (0, 99999)}
        if name in simple:
            (v,) = ints(1, 1)
            rng(v, *simple[name])
            m[name] = v
            return
        if name == "LS":
            a = ints(3, 3)
            rng(a[0], 0, 1)
            rng(a[1], I32MIN, I32MAX)
            rng(a[2], 0, 1)
            m["LS"][str(a[0])] = {"position": a[1], "enable": a[2]}
            return
        if name == "TR":
            a = ints(1, 3)
            for v in a:
                rng(v, I32MIN, I32MAX)
            m["TR"] = a + [0] * (3 - len(a))
            return
        raise ModbusError(2)

    # -- state dump -----------------------------------------------------------------
    def dump(self):
        regs = {}
        for a in sorted(REGMAP):
            mn, idx = REGMAP[a]
            if P[mn]["acc"] == "wo":
                continue
            v = self._param_value(mn) & 0xFFFFFFFF
            regs["0x%04X" % a] = (v >> (16 * idx)) & 0xFFFF
        params = {}
        for mn, p in P.items():
            if p["acc"] == "wo":
                continue
            params[mn] = {"address": "0x%04X" % p["addr"], "words": p["words"],
                          "access": p["acc"], "value": self._param_value(mn)}
        return {
            "device": "Lexium MDrive (LMD) Ethernet, Modbus/TCP (simulated, team lmd-k)",
            "holding_registers": regs,
            "parameters": params,
            "coils": {str(i): self.outputs[i] for i in range(4)},
            "discrete_inputs": {str(i): self.inputs[i] for i in range(4)},
            "manufacturer_functions": copy.deepcopy(self.mfg),
            "status": {
                "not_ready_condition": "logic (aux) supply only, +V motor supply absent"
                if self.cause_present() else None,
                "aux_voltage_V": self.aux_voltage,
                "plus_v_voltage_V": self.plus_v_voltage,
                "VT": self.mfg_read("VT"),
                "IT": self.mfg_read("IT"),
                "EF_error_flag": self.vals["EF"],
                "ER_error_code": self.vals["ER"],
                "AF_hmt_status": self.vals["AF"],
                "LR_locked_rotor": self.vals["LR"],
                "ST_stall": self.vals["ST"],
                "OF_output_fault": self.vals["OF"],
                "MV_moving": self.vals["MV"],
                "MP_moving_to_position": self.vals["MP"],
                "VC_velocity_changing": self.vals["VC"],
                "BY_busy": self.vals["BY"],
                "DE_drive_enable": self.vals["DE"],
                "power_stage_enabled": 0,
                "voltage_warning": 1 if self.cause_present() else 0,
                "temperature_warning": 1 if self.temp_bridge >= self.vals["WT"] else 0,
            },
            "program": dict(self.program),
            "nvm": copy.deepcopy(self.nvm),
            "device_identification": {str(k): v.decode() for k, v in DEV_ID.items()},
            "diagnostic_counters": dict(self.diag),
        }


WO_MNEMONICS = {"ESC", "CP", "EX", "PS", "RS", "E", "HF", "UG"}


def parse_mnemonic(b4):
    s = bytes(reversed(b4)).replace(b"\x00", b" ").decode("latin-1").strip(" ")
    if s == "\x1b":
        return "ESC"
    return s.upper()


# ---------------------------------------------------------------------------
# PDU processing
# ---------------------------------------------------------------------------
def exc(fc, code):
    return bytes([(fc | 0x80) & 0xFF, code])


def process_pdu(drive, pdu):
    fc = pdu[0]
    d = pdu[1:]
    try:
        if fc in (0x01, 0x02):
            if len(d) != 4:
                raise ModbusError(3)
            start = int.from_bytes(d[0:2], "big")
            qty = int.from_bytes(d[2:4], "big")
            if not 1 <= qty <= 2000:
                raise ModbusError(3)
            if start + qty > 4:
                raise ModbusError(2)
            bits = drive.outputs if fc == 1 else drive.inputs
            val = 0
            for i in range(qty):
                val |= bits[start + i] << i
            return bytes([fc, 1, val])
        if fc == 0x05:
            if len(d) != 4:
                raise ModbusError(3)
            addr = int.from_bytes(d[0:2], "big")
            v = int.from_bytes(d[2:4], "big")
            if v not in (0x0000, 0xFF00):
                raise ModbusError(3)
            if addr > 3:
                raise ModbusError(2)
            drive.write_coil(addr, 1 if v else 0)
            return pdu
        if fc == 0x03:
            if len(d) != 4:
                raise ModbusError(3)
            start = int.from_bytes(d[0:2], "big")
            qty = int.from_bytes(d[2:4], "big")
            if not 1 <= qty <= 125:
                raise ModbusError(3)
            if qty > 2:            # one MCode variable per request (manual 898-902, 916)
                raise ModbusError(3)
            words = drive.read_regs(start, qty)
            return bytes([fc, 2 * qty]) + b"".join(w.to_bytes(2, "big") for w in words)
        if fc == 0x10:
            if len(d) < 5:
                raise ModbusError(3)
            start = int.from_bytes(d[0:2], "big")
            qty = int.from_bytes(d[2:4], "big")
            bc = d[4]
            if not 1 <= qty <= 123 or bc != 2 * qty or len(d) != 5 + bc:
                raise ModbusError(3)
            if qty > 2:
                raise ModbusError(3)
            words = [int.from_bytes(d[5 + 2 * i:7 + 2 * i], "big") for i in range(qty)]
            drive.write_regs(start, words)
            return bytes([fc]) + d[0:4]
        if fc == 0x2B:
            if len(d) < 1:
                raise ModbusError(3)
            if d[0] != 0x0E:
                raise ModbusError(1)
            if len(d) != 3:
                raise ModbusError(3)
            code, oid = d[1], d[2]
            if code not in (1, 2, 3, 4):
                raise ModbusError(3)
            if code == 4:
                if oid not in DEV_ID:
                    raise ModbusError(2)
                ids = [oid]
            else:
                last = 2 if code == 1 else 6
                if oid > last:
                    oid = 0
                ids = list(range(oid, last + 1))
            body = b""
            for i in ids:
                body += bytes([i, len(DEV_ID[i])]) + DEV_ID[i]
            return bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)]) + body
        if fc == 0x41:
            if len(d) != 4:
                raise ModbusError(3)
            name = parse_mnemonic(d[0:4])
            if name in WO_MNEMONICS:
                raise ModbusError(2)
            txt = drive.mfg_read(name).encode("ascii")
            return bytes([fc, len(txt)]) + txt
        if fc == 0x42:
            if len(d) < 5:
                raise ModbusError(3)
            name = parse_mnemonic(d[0:4])
            bc = d[4]
            if bc > 28 or len(d) != 5 + bc:
                raise ModbusError(3)
            known = {"AO", "IS", "S1", "S2", "S3", "S4", "S5", "OS", "MU", "RD", "AJ", "AT",
                     "BE", "BL", "BM", "DJ", "DT", "FS", "FL", "LS", "TR", "IT", "VT", "AV",
                     "EL"} | WO_MNEMONICS
            if name not in known:
                raise ModbusError(2)
            drive.mfg_write(name, bytes(d[5:5 + bc]))
            return bytes([fc, bc]) + bytes(d[0:4])
        raise ModbusError(1)
    except ModbusError as e:
        drive.diag["exceptions"] += 1
        return exc(fc, e.code)
    except Exception:  # never let one frame kill the server
        drive.diag["exceptions"] += 1
        return exc(fc, 4)


# ---------------------------------------------------------------------------
# TCP server
# ---------------------------------------------------------------------------
class Server:
    MAX_CONN = 16

    def __init__(self, drive, state_file):
        self.drive = drive
        self.state_file = state_file
        self.conns = set()

    def write_state(self):
        if not self.state_file:
            return
        try:
            tmp = self.state_file + ".tmp"
            with open(tmp, "w") as f:
                json.dump(self.drive.dump(), f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_file)
        except Exception as e:  # noqa
            print("state write failed: %s" % e, file=sys.stderr)

    async def handle(self, reader, writer):
        if len(self.conns) >= self.MAX_CONN:
            writer.close()
            return
        self.conns.add(writer)
        self.drive.diag["connections"] += 1
        try:
            while True:
                hdr = await reader.readexactly(7)
                tid = hdr[0:2]
                pid = int.from_bytes(hdr[2:4], "big")
                length = int.from_bytes(hdr[4:6], "big")
                unit = hdr[6]
                if length < 2 or length > 254:
                    # cannot resynchronise on this stream: drop the connection
                    self.drive.diag["bad_frames"] += 1
                    break
                pdu = await reader.readexactly(length - 1)
                if pid != 0:
                    self.drive.diag["bad_frames"] += 1
                    continue           # not Modbus: discarded silently
                self.drive.diag["requests"] += 1
                resp = process_pdu(self.drive, pdu)
                writer.write(tid + b"\x00\x00" + (len(resp) + 1).to_bytes(2, "big")
                             + bytes([unit]) + resp)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            pass
        finally:
            self.conns.discard(writer)
            try:
                writer.close()
            except Exception:
                pass


async def main_async(args):
    host, _, port = args.listen.rpartition(":")
    drive = Drive()
    srv = Server(drive, args.state)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    loop.add_signal_handler(signal.SIGUSR1, srv.write_state)
    server = await asyncio.start_server(srv.handle, host, int(port), reuse_address=True)
    sock = server.sockets[0]
    print("listening tcp %s:%d" % (host, sock.getsockname()[1]), flush=True)
    await stop.wait()
    server.close()
    for w in list(srv.conns):
        try:
            w.close()
        except Exception:
            pass
    srv.write_state()


def main():
    ap = argparse.ArgumentParser(description="LMD Ethernet Modbus/TCP simulator")
    ap.add_argument("--listen", required=True, help="127.0.0.1:PORT (0 = any free port)")
    ap.add_argument("--state", default=None, help="JSON state dump file")
    args = ap.parse_args()
    host = args.listen.rpartition(":")[0]
    if host not in ("127.0.0.1", "localhost", "::1"):
        ap.error("only loopback addresses are allowed")
    asyncio.run(main_async(args))


if __name__ == "__main__":
    main()

// A MicroPython board on a loopback TCP port: MicroPython's WebAssembly port (npm
// @micropython/micropython-webassembly-pyscript) behind its own raw REPL, for mpremote and deadreckon's uploader
// (`socket://127.0.0.1:PORT`).
//
//   node repl_bridge.mjs [--port N] [--root DIR] [--raw-paste] [--watchdog-ms N]
//
// Prints "LISTENING <port>" when ready. --root DIR is the board's filesystem: loaded into the instance at start,
// written back (mirrored) at every soft reset and when a client disconnects ("SYNCED <files>"; "IDLE" after a
// client has gone).
//
// What the bridge adds to the wasm port, so clients see a board:
// - Ctrl-D on an empty raw REPL is a soft reset: a fresh instance with the same files, "MPY: soft reboot".
// - raw-paste (\x05A\x01) hangs the wasm raw REPL, so the bridge answers it: "R\x00" (refused) by default; with
//   --raw-paste it speaks the protocol itself (window, \x01 flow control, \x04 ack) and feeds the code in raw mode.
// - file errors carry Emscripten errno numbers (44 for ENOENT); tracebacks get MicroPython's usual ones.
// - boot.py/main.py are not run at soft reset (the app needs the board's hardware); the banner says so.
// - --watchdog-ms N: the board's watchdog. With a main.py on the board, the app is taken to run from every boot
//   with the watchdog started and fed by its loop, until the first Ctrl-C stops it (an app that does not hand the
//   watchdog over: the worst case). From then on the watchdog must be fed within N ms through the `machine` module
//   the bridge provides (WDT.feed(), or a machine.Timer's callback, run while the board waits for input as
//   MicroPython's soft timers are), else the board resets ("rst:0x10 (RTCWDT_RTC_RESET)", "WATCHDOG RESET" on
//   stdout): a new instance with the same files, in the friendly REPL, the app running again. A soft reset stops
//   the timers and keeps the watchdog running, as on the ESP32.

import fs from "node:fs";
import net from "node:net";
import path from "node:path";
import { loadMicroPython } from "@micropython/micropython-webassembly-pyscript/micropython.mjs";

const args = process.argv.slice(2);
const option = (name, fallback) => {
  const i = args.indexOf(name);
  return i >= 0 ? args[i + 1] : fallback;
};
const listenPort = parseInt(option("--port", "0"), 10);
const root = option("--root", null);
const offerRawPaste = args.includes("--raw-paste");
const watchdogMs = parseInt(option("--watchdog-ms", "0"), 10);

const SYSTEM_DIRS = new Set(["tmp", "home", "dev", "proc", "peer"]);
const PASTE_WINDOW = 128; // bytes per raw-paste window increment
// Emscripten errno -> MicroPython's (py/mperrno.h) numbers and names
const ERRNO = {
  44: [2, "ENOENT"], 20: [17, "EEXIST"], 31: [21, "EISDIR"], 54: [20, "ENOTDIR"], 55: [39, "ENOTEMPTY"],
  8: [9, "EBADF"], 10: [16, "EBUSY"],
};

let mp = null;
let output = [];
let rawMode = false;
let client = null;

// the watchdog (--watchdog-ms) and the timers that may feed it
const watchdog = { running: false, timeoutMs: watchdogMs, last: Date.now(), appFeeding: false, resets: 0 };
let timers = []; // {id, period, next, once, fn}
let timerIds = 0;
globalThis.peerMachine = {
  wdtStart: (timeout) => {
    watchdog.running = true;
    watchdog.timeoutMs = timeout;
    watchdog.last = Date.now();
  },
  wdtFeed: () => {
    watchdog.last = Date.now();
  },
  timerStart: (period, once, fn) => {
    const id = ++timerIds;
    timers.push({ id, period, next: Date.now() + period, once, fn });
    return id;
  },
  timerStop: (id) => {
    timers = timers.filter((t) => t.id !== id);
  },
};
const MACHINE_PY = `import js
class WDT:
    def __init__(self, id=0, timeout=5000):
        js.peerMachine.wdtStart(timeout)
    def feed(self):
        js.peerMachine.wdtFeed()
class Timer:
    ONE_SHOT = 0
    PERIODIC = 1
    def __init__(self, id=-1, **kw):
        self.id = id
        self.handle = 0
        if kw:
            self.init(**kw)
    def init(self, mode=1, period=-1, callback=None, freq=None):
        if freq:
            period = 1000 // freq
        if period <= 0 or callback is None:
            raise ValueError("period and callback are needed")
        self.deinit()
        self.callback = callback
        self.handle = js.peerMachine.timerStart(period, mode == 0, self._fire)
    def _fire(self):
        self.callback(self)
    def deinit(self):
        if self.handle:
            js.peerMachine.timerStop(self.handle)
            self.handle = 0
`;

async function boot(files, runsApp = true) {
  output = [];
  mp = await loadMicroPython({ stdout: (d) => output.push(...d), linebuffer: false, heapsize: 2 * 1024 * 1024 });
  timers = [];
  if (watchdogMs > 0) {
    mp.FS.mkdir("/peer");
    mp.FS.writeFile("/peer/machine.py", MACHINE_PY);
    mp.runPython("import sys\nsys.path.append('/peer')");
    if (runsApp && files.some(([rel, data]) => rel === "main.py" && data !== null)) {
      watchdog.running = true; // the app starts it and feeds it from its loop
      watchdog.appFeeding = true;
      watchdog.timeoutMs = watchdogMs;
    }
    watchdog.last = Date.now();
  }
  for (const [rel, data] of files) {
    const parts = rel.split("/");
    for (let i = 1; i < parts.length; i++) {
      const dir = "/" + parts.slice(0, i).join("/");
      if (!mp.FS.analyzePath(dir).exists) mp.FS.mkdir(dir);
    }
    if (data === null) {
      if (!mp.FS.analyzePath("/" + rel).exists) mp.FS.mkdir("/" + rel);
    } else {
      mp.FS.writeFile("/" + rel, data);
    }
  }
  mp.FS.chdir("/");
  mp.replInit();
}

// every file and folder of the instance's filesystem, as [relpath, Uint8Array | null for a folder]
function snapshot() {
  const found = [];
  const walk = (dir, rel) => {
    for (const name of mp.FS.readdir(dir)) {
      if (name === "." || name === "..") continue;
      if (rel === "" && SYSTEM_DIRS.has(name)) continue;
      const full = dir === "/" ? "/" + name : dir + "/" + name;
      const relName = rel ? rel + "/" + name : name;
      const stat = mp.FS.stat(full);
      if (mp.FS.isDir(stat.mode)) {
        found.push([relName, null]);
        walk(full, relName);
      } else {
        found.push([relName, mp.FS.readFile(full)]);
      }
    }
  };
  walk("/", "");
  return found;
}

function loadRoot() {
  const files = [];
  if (!root || !fs.existsSync(root)) return files;
  const walk = (dir, rel) => {
    for (const entry of fs.readdirSync(dir, { withFileTypes: true })) {
      const relName = rel ? rel + "/" + entry.name : entry.name;
      if (entry.isDirectory()) {
        files.push([relName, null]);
        walk(path.join(dir, entry.name), relName);
      } else {
        files.push([relName, new Uint8Array(fs.readFileSync(path.join(dir, entry.name)))]);
      }
    }
  };
  walk(root, "");
  return files;
}

function syncRoot() {
  if (!root) return;
  const files = snapshot();
  fs.rmSync(root, { recursive: true, force: true });
  fs.mkdirSync(root, { recursive: true });
  for (const [rel, data] of files) {
    const target = path.join(root, ...rel.split("/"));
    if (data === null) fs.mkdirSync(target, { recursive: true });
    else {
      fs.mkdirSync(path.dirname(target), { recursive: true });
      fs.writeFileSync(target, data);
    }
  }
  console.log(`SYNCED ${files.filter(([, d]) => d !== null).length}`);
}

function fixErrnos(text) {
  return text
    .replace(/OSError: (\d+)\r\n/g, (m, n) => (ERRNO[n] ? `OSError: [Errno ${ERRNO[n][0]}] ${ERRNO[n][1]}\r\n` : m))
    .replace(/\[Errno (\d+)\] E[A-Z]+/g, (m, n) => (ERRNO[n] ? `[Errno ${ERRNO[n][0]}] ${ERRNO[n][1]}` : m));
}

function flush() {
  if (!output.length) return;
  const text = fixErrnos(Buffer.from(output).toString("latin1"));
  output = [];
  if (client) client.write(Buffer.from(text, "latin1"));
}

function send(bytes) {
  flush();
  if (client) client.write(Buffer.from(bytes, "latin1"));
}

async function softReset() {
  flush();
  const files = snapshot();
  syncRoot();
  const wasRaw = rawMode;
  await boot(files, !wasRaw); // from the raw REPL MicroPython's soft reset does not run main.py
  if (wasRaw) mp.replProcessChar(0x01);
  output = [];
  if (wasRaw) send("MPY: soft reboot\r\nraw REPL; CTRL-B to exit\r\n>");
  else send("MPY: soft reboot\r\n(boot.py/main.py not run on this peer)\r\nMicroPython v1.27.0 (wasm peer)\r\n>>> ");
}

// input handling: a small state machine in front of the REPL, fed one byte at a time
let pending = []; // bytes of a possible raw-paste request
let paste = null; // {code: [], sinceGrant: n} while receiving a raw paste
let rawLineEmpty = true; // nothing typed since the last raw-REPL prompt
let queue = Promise.resolve();

async function feed(byte) {
  if (paste) {
    if (byte === 0x04) {
      const code = paste.code;
      paste = null;
      send("\x04"); // all data received
      for (const c of code) mp.replProcessChar(c);
      output = [];
      mp.replProcessChar(0x04);
      let text = Buffer.from(output).toString("latin1");
      output = [];
      if (text.startsWith("OK")) text = text.slice(2);
      send(fixErrnos(text));
      rawLineEmpty = true;
      return;
    }
    paste.code.push(byte);
    if (++paste.sinceGrant >= PASTE_WINDOW) {
      paste.sinceGrant -= PASTE_WINDOW;
      send("\x01");
    }
    return;
  }
  if (rawMode && rawLineEmpty && (pending.length || byte === 0x05)) {
    pending.push(byte);
    const expected = [0x05, 0x41, 0x01];
    if (pending.every((b, i) => b === expected[i])) {
      if (pending.length < 3) return;
      pending = [];
      if (offerRawPaste) {
        paste = { code: [], sinceGrant: 0 };
        send(Buffer.from([0x52, 0x01, PASTE_WINDOW & 0xff, PASTE_WINDOW >> 8]).toString("latin1"));
      } else {
        send("R\x00");
      }
      return;
    }
    const held = pending;
    pending = [];
    for (const b of held) await process1(b);
    return;
  }
  await process1(byte);
}

async function watchdogReset() {
  flush();
  const files = snapshot();
  syncRoot();
  watchdog.running = false; // a reset stops it; the app starts it again
  watchdog.appFeeding = false;
  watchdog.resets += 1;
  rawMode = false;
  pending = [];
  paste = null;
  rawLineEmpty = true;
  await boot(files);
  output = [];
  console.log("WATCHDOG RESET");
  send("\r\nets Jul 29 2019 12:21:46\r\n\r\nrst:0x10 (RTCWDT_RTC_RESET),boot:0x13 (SPI_FAST_FLASH_BOOT)\r\n" +
       "(boot.py/main.py not run on this peer)\r\nMicroPython v1.27.0 (wasm peer)\r\n>>> ");
}

// every 10 ms, while the board waits for input: the timers due run (MicroPython's soft timers), then the watchdog
// is checked
if (watchdogMs > 0) {
  setInterval(() => {
    queue = queue.then(async () => {
      const now = Date.now();
      for (const t of timers.slice()) {
        if (now < t.next) continue;
        t.next = now + t.period;
        if (t.once) timers = timers.filter((x) => x !== t);
        try {
          t.fn();
        } catch (e) {
          console.log(`TIMER ERROR ${e}`);
        }
      }
      output = []; // a callback's prints are not part of a REPL reply here
      if (watchdog.running && !watchdog.appFeeding && Date.now() - watchdog.last > watchdog.timeoutMs) {
        await watchdogReset();
      }
    });
  }, 10);
}

async function process1(byte) {
  if (byte === 0x03 && watchdog.appFeeding) {
    watchdog.appFeeding = false; // Ctrl-C stops the app: its loop fed the watchdog a moment ago, and no more
    watchdog.last = Date.now();
  }
  if (byte === 0x01) rawMode = true;
  else if (byte === 0x02) rawMode = false;
  if (rawMode && byte === 0x04 && rawLineEmpty) {
    await softReset();
    return;
  }
  const exit = mp.replProcessChar(byte);
  if (exit) {
    await softReset();
    return;
  }
  if (rawMode) {
    if (byte === 0x04 || byte === 0x03 || byte === 0x01) rawLineEmpty = true;
    else rawLineEmpty = false;
  }
}

await boot(loadRoot());
output = [];

const server = net.createServer((socket) => {
  if (client) {
    socket.end(); // a serial port has one user
    return;
  }
  client = socket;
  socket.setNoDelay(true);
  socket.on("data", (data) => {
    queue = queue.then(async () => {
      for (const byte of data) await feed(byte);
      flush();
    });
  });
  const done = () => {
    if (client !== socket) return;
    queue = queue.then(() => {
      client = null;
      pending = [];
      paste = null;
      syncRoot();
      console.log("IDLE");
    });
  };
  socket.on("end", done);
  socket.on("close", done);
  socket.on("error", done);
});
server.listen(listenPort, "127.0.0.1", () => console.log(`LISTENING ${server.address().port}`));

"""Load the status page of a running demo gateway in headless Chromium and check what a person
sees: the bus and the four demo drives in the tables, in the trace panel a request sent after the
page loaded, its master among the connected ones, and with the slave filter set, that slave's
frames alone; in the plant values, each labelled by its help text with its metric's name beneath,
drive 2's output frequency rising after a run command written to the drive, its plot gaining
points, showing its lowest and highest reading and the time it spans, and under a mouse moved
over it the reading there; a value whose polls fail (on a slave that is not on the line) marked
as failed in words and colour; in the last writes, none before the run command, then its two
writes answered, and a write to drive 4 acknowledged unsent by the check's [[rule]]. At 1280, 800,
700 and 390 px wide: no sideways scroll of the page, every caption in full view outside any
scroll box, and each write's outcome in view without scrolling sideways.
Fails on a script error or a Content-Security-Policy violation in the page.

Chromium is driven over the DevTools protocol on a pipe (--remote-debugging-pipe: JSON messages
ending in NUL, commands on fd 3, replies and events on fd 4), so the standard library is enough.

Usage: status-page-browser.py METRICS_PORT MODBUS_PORT [--screenshot PATH]
"""

import base64
import fcntl
import json
import os
import select
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

CHROMIUM = os.environ.get("CHROMIUM", "chromium")
WAIT = 20.0  # seconds for anything the page should show

# What the page must show of config/demo.toml: its bus, and its drives by address and model.
DEMO_BUS = "demo"
DEMO_DRIVES = {1: "gd20", 2: "gd300", 3: "gd10", 4: "pd-inverter"}

# Drive 2's plant value in config/demo.toml (its goodrive300 template: 3000H in 0.01 Hz, its help
# text), polled every 2 s.
FREQUENCY = "drive_output_frequency_hertz"
FREQUENCY_HELP = "Output frequency"
FREQUENCY_SLAVE = 2
# After the run command, the page must show this many successive readings, each higher than the
# one before (the drive ramps from 0 to 50.00 Hz in 15 s, P00.11), and its plot as many more
# points.
RISING_READINGS = 3

# The [[rule]] .ci/status-page-check adds to the demo: writes to this unit are acknowledged unsent.
RULE = "drive 4 on trial"
ACKNOWLEDGED_UNIT = 4
# Drive 4's frequency reference (percent of P0-10, in 0.01 %), which the check writes there.
ACKNOWLEDGED_REGISTER = 0x1000
# The last writes' empty line.
NO_WRITES = "no writes since the gateway started"
# Why the rule's write was not sent, in the journal's words, shown under its outcome.
ACKNOWLEDGED_WHY = "answered by the gateway as the slave would have; not sent"

# The slave .ci/status-page-check adds to the demo, which is not on the line: its one value, the
# same metric as drive 2's (so with the same help), fails its polls as one of these outcomes.
FAILED_SLAVE = 9
FAILED_OUTCOMES = ("timeout", "slave_down")

# A laptop, its half screen, a narrower window and a phone: the page must fit; only tables may
# scroll sideways, inside their own box, their captions outside it.
WIDTHS = (1280, 800, 700, 390)

# How wide the page is laid out against its viewport (scrollbars are hidden, so clientWidth is the
# viewport's width); wider means the reader scrolls the whole page sideways.
PAGE_WIDTH = """JSON.stringify({
  page: document.documentElement.scrollWidth,
  client: document.documentElement.clientWidth,
  widest: [...document.body.querySelectorAll('*')]
    .filter(e => e.getBoundingClientRect().right > document.documentElement.clientWidth + 1)
    .slice(0, 5).map(e => e.tagName + (e.id ? '#' + e.id : '') + ' ' +
      Math.round(e.getBoundingClientRect().right) + ' px'),
})"""

# What a reader sees sideways at this width: for every caption (`caption` elements and those the
# page styles as captions), every write's outcome cell and every failed value's "poll failed",
# why it is not wholly in view, or null.
# In view: inside the viewport's width, its text not overflowing its box, and inside the box of
# every ancestor that clips (a scroll box, or paint containment), that box not scrolled; a caption
# must be in no scroll box at all, so that it never scrolls away with its table.
LAYOUT = """(() => {
  const view = document.documentElement.clientWidth;
  const name = (e) => e.tagName.toLowerCase() + (e.id ? '#' + e.id : '') +
    (e.className && typeof e.className === 'string' ? '.' + e.className.split(' ').join('.') : '');
  const hidden = (e, caption) => {
    const box = e.getBoundingClientRect();
    if (box.width === 0 || box.height === 0) return 'not shown';
    if (box.left < -0.5 || box.right > view + 0.5)
      return `outside the viewport: ${Math.round(box.left)} to ${Math.round(box.right)} of ${view} px`;
    if (e.scrollWidth > e.clientWidth + 1)
      return `its text overflows its box: ${e.scrollWidth} > ${e.clientWidth} px`;
    for (let a = e.parentElement; a && a !== document.documentElement; a = a.parentElement) {
      const style = getComputedStyle(a);
      const scrolls = style.overflowX !== 'visible';
      if (scrolls && caption) return 'inside the scroll box ' + name(a);
      if (!scrolls && !/paint|strict|content/.test(style.contain) &&
          style.contentVisibility !== 'auto') continue;
      if (a.scrollLeft !== 0) return name(a) + ' is scrolled sideways';
      const outer = a.getBoundingClientRect();
      if (box.left < outer.left - 0.5 || box.right > outer.right + 0.5)
        return `cut by ${name(a)}: ${Math.round(box.left)} to ${Math.round(box.right)} px in ` +
          `${Math.round(outer.left)} to ${Math.round(outer.right)}`;
    }
    return null;
  };
  return JSON.stringify({
    captions: [...document.querySelectorAll('caption, .caption')].map(e =>
      ({text: e.textContent, hidden: hidden(e, true)})),
    groups: document.querySelectorAll('#values .slave-values').length,
    outcomes: [...document.querySelectorAll('#writes tr[data-id] td.outcome')].map(e =>
      ({text: e.textContent, hidden: hidden(e, false)})),
    marks: [...document.querySelectorAll('#values tr.failed .failed-mark')].map(e =>
      ({text: e.textContent, hidden: hidden(e, false)})),
  });
})()"""

# What the tables, the trace state and the trace rows hold, as text (nothing yet while the page
# loads).
SNAPSHOT = """JSON.stringify({
  buses: [...document.querySelectorAll('#buses tr[data-bus]')].map(r =>
    ({bus: r.dataset.bus, text: r.textContent})),
  slaves: [...document.querySelectorAll('#slaves tr[data-slave]')].map(r =>
    ({bus: r.dataset.bus, slave: Number(r.dataset.slave), text: r.textContent})),
  masters: document.getElementById('masters')?.textContent ?? '',
  trace: document.getElementById('trace-state')?.textContent ?? '',
  problem: document.getElementById('problem')?.textContent ?? '',
  updated: document.getElementById('updated')?.textContent ?? '',
  'drive 3': document.querySelector('#slaves tr[data-slave="3"] td:nth-child(5)')?.textContent ?? '',
  // The last writes, newest first: each row's id, unit and outcome, and its cells' text.
  writes: [...document.querySelectorAll('#writes tr')].map(r =>
    ({id: r.dataset.id === undefined ? null : Number(r.dataset.id),
      unit: r.dataset.unit === undefined ? null : Number(r.dataset.unit),
      outcome: r.dataset.outcome ?? null, cells: [...r.cells].map(c => c.textContent)})),
  // The virtual units' registers: each row's cells.
  virtual: [...document.querySelectorAll('#virtual tr')].map(r => [...r.cells].map(c => c.textContent)),
  frames: [...document.querySelectorAll('#trace tr')].map(r =>
    ({direction: r.dataset.direction, slave: Number(r.dataset.slave), bus: r.dataset.bus,
      cells: [...r.cells].map(c => c.textContent)})),
  // Each value's row: name, reading, age, last poll; and the readings its plot draws (one "M" or
  // "L" each in its path). Its label (help) and the metric's name beneath: their text, font size
  // and where the name's top is against the label's bottom; whether the row is marked failed, and
  // the colour of its reading. Its plot's scale (max, min, from, to) and the reading under the
  // pointer, while one points at it.
  values: [...document.querySelectorAll('#values tr[data-name]')].map(r => {
    const help = r.querySelector('.help'), metric = r.querySelector('.metric');
    const text = (selector) => r.querySelector(selector)?.textContent ?? null;
    return {bus: r.dataset.bus, slave: Number(r.dataset.slave), name: r.dataset.name,
      cells: [...r.cells].slice(0, 4).map(c => c.textContent),
      points: (r.querySelector('path.line')?.getAttribute('d') ?? '').split(/[ML]/).length - 1,
      help: help?.textContent ?? null, metric: metric?.textContent ?? null,
      sizes: [help, metric].map(e => e ? parseFloat(getComputedStyle(e).fontSize) : null),
      beneath: help && metric && help.getBoundingClientRect().height > 0 ?
        metric.getBoundingClientRect().top - help.getBoundingClientRect().bottom : null,
      failed: r.classList.contains('failed'), mark: text('.failed-mark'),
      colours: [help, r.querySelector('.failed-mark')].map(e => e ? getComputedStyle(e).color : null),
      max: text('.plot-max'), min: text('.plot-min'), from: text('.plot-from'), to: text('.plot-to'),
      pointing: r.querySelector('.plot').classList.contains('pointing'),
      pointer: text('.plot-pointer'), dot: r.querySelector('path.dot')?.getAttribute('d') ?? null};
  }),
})"""

# The page's own pure functions, on inputs the demo does not produce: what each must return.
PAGE_FUNCTIONS = {
    'reading(6.390000000000001, "Hz")': "6.39 Hz",
    'reading(null, "Hz")': "–",
    'reading(1234567.5, "")': "1234568",
    'reading(-3, null)': "-3",
    # A lone reading is a dot; a silence of three usual spacings or more breaks the line.
    'sparkline([[1000, 7]]).path': "M0.000 50h0",
    'sparkline([[0, 0], [1000, 10], [2000, 5], [9000, 5], [10000, 0]]).path':
        "M0.000 100.00h0L1.000 0.00L2.000 50.00M9.000 50.00h0L10.000 100.00",
    # The pointer reads the nearest reading within reach, or none.
    'JSON.stringify(nearest([[0, 1], [1000, 2], [5000, 3]], 1400, 500))': "[1000,2]",
    'nearest([[0, 1], [1000, 2]], 3000, 1000)': None,
    'nearest([], 0, Infinity)': None,
    # A value without help is labelled by its name alone; labels go beneath.
    'valueName({name: "x_total", help: "x_total", labels: {}}).textContent': "x_total",
    'valueName({name: "x_total", help: "X", labels: {pump: "2"}}).querySelector(".metric")'
    '.textContent': "x_total pump=2",
    # A write's cells: registers as a rule names them, values a register to a group, the outcome
    # with its exception and whether it may have been carried out.
    'writeRegisters({table: "holding", start: 8192, count: 2})': "holding 0x2000–0x2001 (2)",
    'writeRegisters({table: "coil", start: 5, count: 1})': "coil 0x0005",
    'writeRegisters({function: 8, values: "0001FF00"})': "–",
    'writeValues({table: "holding", values: "13880032"}).textContent': "1388 0032",
    'writeValues({table: "coil", values: "CD01"}).textContent': "CD 01",
    'writeFunction(0x10).textContent': "Write Multiple Registers",
    'writeFunction(0x41).textContent': "0x41",
    'writeOutcome(null).textContent': "pending",
    'writeOutcome({outcome: "slave_exception", carried_out: "no", exception: 2}).textContent':
        "slave_exception, exception 0x02",
    # Why, in words, shown under it (a phone has no tooltips).
    'writeOutcome({outcome: "denied", carried_out: "no", exception: 1, detail: "rule 2"})'
    '.querySelector(".why").textContent': "rule 2",
    '(() => { const td = writeOutcome({outcome: "timeout", carried_out: "maybe", exception: 11}); '
    'return td.firstChild.textContent + " / " + td.querySelector(".note").textContent; })()':
        "timeout, exception 0x0B / may have been carried out",
    # A master's certificate subject is its own to choose: it must stay text.
    '(() => { const td = writeMaster({master: "10.0.0.7:502", protocol: "tls", role: "operator", '
    'subject: "CN=<b>x</b>"}); return td.textContent + " " + td.querySelectorAll("b").length; })()':
        "10.0.0.7:502 tls, role operator, CN=<b>x</b> 0",
}


class Browser:
    """One headless Chromium and one page in it."""

    def __init__(self, log):
        self.profile = tempfile.mkdtemp(prefix="status-page-check-")
        commands_read, self.commands = os.pipe()
        self.events, events_write = os.pipe()
        # Out of the way of fds 3 and 4, which the child gets them as.
        high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (commands_read, events_write)]
        for fd in (commands_read, events_write):
            os.close(fd)

        def child_fds():
            os.dup2(high[0], 3)
            os.dup2(high[1], 4)

        self.process = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
             "--hide-scrollbars", "--remote-debugging-pipe", "--window-size=1280,900",
             f"--user-data-dir={self.profile}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=log, stderr=log,
            pass_fds=(3, 4), preexec_fn=child_fds)
        for fd in high:
            os.close(fd)
        self.buffer = b""
        self.next_id = 0
        self.session = None
        self.problems = []  # script errors and policy violations seen in the page

    def close(self):
        self.process.kill()
        self.process.wait()
        os.close(self.commands)
        os.close(self.events)
        shutil.rmtree(self.profile, ignore_errors=True)

    def _message(self, deadline):
        while b"\0" not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.events], [], [], left)[0]:
                raise TimeoutError("no answer from Chromium")
            chunk = os.read(self.events, 65536)
            if not chunk:
                raise RuntimeError("Chromium closed its DevTools pipe")
            self.buffer += chunk
        message, self.buffer = self.buffer.split(b"\0", 1)
        return json.loads(message)

    def _event(self, message):
        method, params = message.get("method"), message.get("params", {})
        if method == "Runtime.exceptionThrown":
            self.problems.append("script error: " + json.dumps(params["exceptionDetails"]))
        elif method == "Log.entryAdded":
            entry = params["entry"]
            if entry.get("source") in ("security", "javascript") or \
                    "Content Security Policy" in entry.get("text", ""):
                self.problems.append(f"{entry.get('source')}: {entry.get('text')}")

    def call(self, method, params=None, session=True):
        self.next_id += 1
        command = {"id": self.next_id, "method": method, "params": params or {}}
        if session and self.session:
            command["sessionId"] = self.session
        os.write(self.commands, json.dumps(command).encode() + b"\0")
        deadline = time.monotonic() + WAIT
        while True:
            message = self._message(deadline)
            if message.get("id") == self.next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]
            self._event(message)

    def open(self, url):
        target = self.call("Target.createTarget", {"url": "about:blank"}, session=False)
        attached = self.call("Target.attachToTarget",
                             {"targetId": target["targetId"], "flatten": True}, session=False)
        self.session = attached["sessionId"]
        self.call("Runtime.enable")
        self.call("Log.enable")
        self.call("Emulation.setDeviceMetricsOverride",
                  {"width": 1280, "height": 900, "deviceScaleFactor": 1, "mobile": False})
        self.call("Page.navigate", {"url": url})

    def resize(self, width):
        self.call("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": 900, "deviceScaleFactor": 1, "mobile": False})

    def wait_for_layout(self, width):
        """The page's width and its viewport's once the page is laid out at `width` px."""
        deadline = time.monotonic() + WAIT
        while True:
            widths = json.loads(self.evaluate(PAGE_WIDTH))
            if widths["client"] == width or time.monotonic() > deadline:
                return widths
            time.sleep(0.1)

    def mouse(self, x, y):
        """Move the mouse to (`x`, `y`), CSS pixels of the viewport."""
        self.call("Input.dispatchMouseEvent", {"type": "mouseMoved", "x": x, "y": y})

    def evaluate(self, expression):
        result = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        if "exceptionDetails" in result:
            raise RuntimeError(f"evaluate: {result['exceptionDetails']}")
        return result["result"].get("value")

    def snapshot(self):
        return json.loads(self.evaluate(SNAPSHOT))

    def wait_for(self, what, check):
        """Poll the page until `check(snapshot)` is true; fail naming `what`."""
        deadline = time.monotonic() + WAIT
        while True:
            snapshot = self.snapshot()
            if self.problems:
                fail("the page reported problems", self.problems)
            if check(snapshot):
                return snapshot
            if time.monotonic() > deadline:
                fail(f"the page never showed {what}", snapshot)
            time.sleep(0.1)

    def screenshot(self, path):
        shot = self.call("Page.captureScreenshot", {"format": "png"})
        with open(path, "wb") as file:
            file.write(base64.b64decode(shot["data"]))


def fail(what, detail):
    print(f"status page check FAILED: {what}\n{json.dumps(detail, indent=1)}", file=sys.stderr)
    raise SystemExit(1)


def crc16(frame):
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


class Master:
    """A Modbus TCP master on a plain socket."""

    def __init__(self, port):
        self.socket = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.transaction = 0

    def address(self):
        host, port = self.socket.getsockname()[:2]
        return f"{host}:{port}"

    def read(self, unit, register, count):
        """Read holding registers; the RTU frame the gateway sends for it, as the trace shows it."""
        self.transaction += 1
        pdu = struct.pack(">BHH", 3, register, count)
        self.socket.sendall(struct.pack(">HHHB", self.transaction, 0, len(pdu) + 1, unit) + pdu)
        header = self.socket.recv(7, socket.MSG_WAITALL)
        length = struct.unpack(">H", header[4:6])[0]
        self.socket.recv(length - 1, socket.MSG_WAITALL)
        frame = bytes([unit]) + pdu
        return " ".join(f"{b:02x}" for b in frame + crc16(frame))

    def write(self, unit, register, value):
        """Write one holding register (06); fail naming the exception if the unit refuses."""
        self.transaction += 1
        pdu = struct.pack(">BHH", 6, register, value)
        self.socket.sendall(struct.pack(">HHHB", self.transaction, 0, len(pdu) + 1, unit) + pdu)
        header = self.socket.recv(7, socket.MSG_WAITALL)
        length = struct.unpack(">H", header[4:6])[0]
        reply = self.socket.recv(length - 1, socket.MSG_WAITALL)
        if reply != pdu:
            fail(f"writing {value} to {register:04X}H of unit {unit}", {"reply": reply.hex(" ")})

    def close(self):
        self.socket.close()


def age(text):
    """Seconds in an age the page shows ("just now", "12 s ago", "1 min 3 s ago"); -1 if not one."""
    if text == "just now":
        return 0
    words = text.split()
    if not words or words[-1] != "ago":
        return -1
    seconds = 0
    for number, unit in zip(words[0:-1:2], words[1:-1:2]):
        if not number.isdigit() or unit not in ("s", "min", "h", "d"):
            return -1
        seconds += int(number) * {"s": 1, "min": 60, "h": 3600, "d": 86400}[unit]
    return seconds


def frequency(snapshot):
    """Drive 2's output frequency as the page shows it: its row, or None."""
    return value_row(snapshot, FREQUENCY_SLAVE)


def hertz(row):
    """The reading in a value's row if it is a number of Hz ("37.52 Hz"), else None."""
    number, _, unit = (row or {"cells": ["", ""]})["cells"][1].partition(" ")
    try:
        return float(number) if unit == "Hz" else None
    except ValueError:
        return None


def follows_a_write(browser, port):
    """Drive 2 set to 50.00 Hz and run forward: the frequency the page shows must rise through
    RISING_READINGS successive readings and its plot gain as many points. Returns the readings."""
    before = frequency(browser.wait_for(
        f"drive {FREQUENCY_SLAVE}'s {FREQUENCY} in Hz with a plot",
        lambda s: hertz(frequency(s)) is not None and frequency(s)["points"] > 0))
    master = Master(port)
    master.write(FREQUENCY_SLAVE, 0x2001, 5000)  # frequency reference: 50.00 Hz
    master.write(FREQUENCY_SLAVE, 0x2000, 1)  # run forward
    master.close()
    readings = [hertz(before)]
    deadline = time.monotonic() + WAIT
    while True:
        snapshot = browser.snapshot()
        if browser.problems:
            fail("the page reported problems", browser.problems)
        row = frequency(snapshot)
        shown = hertz(row)
        if shown is not None and shown != readings[-1]:
            if shown < readings[-1]:
                fail(f"drive {FREQUENCY_SLAVE}'s frequency on the page fell while the drive ramps "
                     "up", {"readings": readings + [shown], "row": row})
            readings.append(shown)
        gained = row["points"] - before["points"] if row else 0
        if len(readings) > RISING_READINGS and gained >= RISING_READINGS:
            return readings, before["points"], row["points"]
        if time.monotonic() > deadline:
            fail(f"the page did not follow drive {FREQUENCY_SLAVE}'s ramp within {WAIT:.0f} s: "
                 f"wanted {RISING_READINGS} rising readings after {readings[0]} Hz and "
                 f"{RISING_READINGS} more points in the plot",
                 {"readings": readings, "points before": before["points"], "row": row})
        time.sleep(0.2)


# A write's row: its outcome first (then why, in words, if the journal says), then when, the unit
# and where it went, the function, registers, values, rule and action, and the master.
OUTCOME, TIME, TARGET, FUNCTION, REGISTERS, VALUES, RULE_ACTION, MASTER = range(8)


def write_row(snapshot, unit, register_text):
    """The newest row of the last writes for `unit` whose registers read `register_text`."""
    return next((w for w in snapshot["writes"]
                 if w["unit"] == unit and len(w["cells"]) == 8
                 and w["cells"][REGISTERS] == register_text),
                None)


def shows_writes(browser, port):
    """After the run command's writes to drive 2 (answered by the drive, no rule), a write to
    drive 4 that the check's [[rule]] acknowledges unsent: the last writes must show it first,
    with its rule and outcome. Returns the rows."""
    master = Master(port)
    master.write(ACKNOWLEDGED_UNIT, ACKNOWLEDGED_REGISTER, 2500)  # 25.00 %
    master.close()
    run = "holding 0x2000"  # the run command of follows_a_write
    kept = f"holding 0x{ACKNOWLEDGED_REGISTER:04X}"
    snapshot = browser.wait_for(
        f"the write to drive {ACKNOWLEDGED_UNIT} acknowledged by the rule \"{RULE}\" first in the "
        "last writes, after drive 2's run command answered",
        lambda s: s["writes"] and s["writes"][0]["unit"] == ACKNOWLEDGED_UNIT
        and s["writes"][0]["outcome"] == "acknowledged"
        and (write_row(s, FREQUENCY_SLAVE, run) or {}).get("outcome") == "answered")
    acknowledged, answered = snapshot["writes"][0], write_row(snapshot, FREQUENCY_SLAVE, run)
    wanted = {
        "acknowledged": (acknowledged, {
            OUTCOME: "acknowledged" + ACKNOWLEDGED_WHY,
            TARGET: f"{ACKNOWLEDGED_UNIT} → {DEMO_BUS} / {ACKNOWLEDGED_UNIT}",
            FUNCTION: "Write Single Register", REGISTERS: kept, VALUES: "09C4",
            RULE_ACTION: f"{RULE}: acknowledge"}),
        "answered": (answered, {
            OUTCOME: "answered",
            TARGET: f"{FREQUENCY_SLAVE} → {DEMO_BUS} / {FREQUENCY_SLAVE}",
            FUNCTION: "Write Single Register", REGISTERS: run, VALUES: "0001",
            RULE_ACTION: "no rule: allow"}),
    }
    for what, (row, cells) in wanted.items():
        wrong = {i: row["cells"][i] for i, text in cells.items() if row["cells"][i] != text}
        if wrong or age(row["cells"][TIME]) < 0 or "127.0.0.1:" not in row["cells"][MASTER]:
            fail(f"the {what} write's row in the last writes", {"row": row, "wanted": cells})
    ids = [w["id"] for w in snapshot["writes"]]
    if ids != sorted(ids, reverse=True) or len(ids) != 3:
        fail("the three writes, newest first", snapshot["writes"])
    return snapshot["writes"]


# The plot's least width, as the page has it (PLOT_MIN_SECONDS): its time scale starts at least
# this many seconds ago.
PLOT_MIN_SECONDS = 60


def value_row(snapshot, slave, name=FREQUENCY):
    """The row of `slave`'s value `name` on the demo bus, or None."""
    return next((v for v in snapshot["values"] if v["bus"] == DEMO_BUS
                 and v["slave"] == slave and v["name"] == name), None)


def labelled_by_help(browser, metrics_port):
    """Every value's row labelled by its help as /values gives it, the metric's name (and labels)
    beneath it in smaller type unless the label is the name itself; drive 2's frequency by its
    template's help. Returns how many values there are."""
    url = f"http://127.0.0.1:{metrics_port}/values"
    with urllib.request.urlopen(url, timeout=10) as answer:
        values = json.load(answer)["values"]
    snapshot = browser.wait_for(f"a row for each of the {len(values)} plant values",
                                lambda s: len(s["values"]) == len(values))
    wrong = []
    for value in values:
        row = value_row(snapshot, value["slave"], value["name"])
        labels = ", ".join(f"{k}={x}" for k, x in value["labels"].items())
        name = "" if value["help"] == value["name"] else value["name"]
        metric = " ".join(filter(None, [name, labels])) or None
        if row is None or row["help"] != value["help"] or row["metric"] != metric or (
                metric and not (row["beneath"] is not None and row["beneath"] >= -1
                                and row["sizes"][1] < row["sizes"][0])):
            wrong.append({"value": value, "wanted metric": metric, "row": row})
    if wrong:
        fail(f"{len(wrong)} plant values not labelled by their help text with the metric's name "
             "beneath in smaller type", wrong[:5])
    row = value_row(snapshot, FREQUENCY_SLAVE)
    if row["help"] != FREQUENCY_HELP or row["metric"] != FREQUENCY:
        fail(f"drive {FREQUENCY_SLAVE}'s {FREQUENCY} labelled \"{FREQUENCY_HELP}\"", row)
    return len(values)


def shows_scale(snapshot):
    """Drive 2's frequency plot, after the ramp began, between the drive's 0 Hz before the run
    command (its lowest) and the reading now (its highest, the drive ramping up), from at least a
    minute ago to now."""
    row = value_row(snapshot, FREQUENCY_SLAVE)
    return row is not None and row["min"] == "min 0 Hz" and hertz(row) \
        and row["max"] == "max " + row["cells"][1] \
        and age(row["from"]) >= PLOT_MIN_SECONDS and row["to"] == "now"


def marks_failed(snapshot):
    """The value of the slave that is not on the line marked failed: "poll failed" and the
    outcome under its label, in another colour than the label's, the outcome as its last poll,
    no reading, a bar down its row (the class that draws it); and drive 2's value not so
    marked."""
    row, good = value_row(snapshot, FAILED_SLAVE), value_row(snapshot, FREQUENCY_SLAVE)
    return row is not None and good is not None and row["failed"] and not good["failed"] \
        and not good["mark"] and row["help"] == FREQUENCY_HELP \
        and row["cells"][3] in FAILED_OUTCOMES and row["mark"] == "poll failed: " + row["cells"][3] \
        and row["colours"][1] != row["colours"][0] and row["cells"][1] == "–"


def fits(browser, width):
    """At `width` px: no sideways scroll of the page, every caption, each write's outcome and the
    failed value's mark in full view (LAYOUT). Returns how many captions there are."""
    browser.resize(width)
    scroll = browser.wait_for_layout(width)
    if scroll["page"] > scroll["client"]:
        fail(f"the page scrolls sideways at {width} px (tables must scroll in their own box)",
             scroll)
    layout = json.loads(browser.evaluate(LAYOUT))
    # Connected masters, last writes, live trace, and one per slave with plant values.
    if len(layout["captions"]) < 3 + layout["groups"] or len(layout["outcomes"]) != 3 \
            or len(layout["marks"]) != 1:
        fail(f"the captions, the three writes' outcomes and the failed value's mark at {width} px",
             layout)
    hidden = [c for c in layout["captions"] + layout["outcomes"] + layout["marks"] if c["hidden"]]
    if hidden:
        fail(f"captions, writes' outcomes or the failed value's mark not wholly in view at "
             f"{width} px", hidden)
    return len(layout["captions"])


# Where drive 2's frequency plot's first and last readings are on the screen (CSS pixels), once
# it is scrolled into view: from the x of each reading in its path and its viewBox.
PLOT_POINTS = """(() => {
  const row = [...document.querySelectorAll('#values tr[data-name]')].find(r =>
    r.dataset.bus === %s && r.dataset.slave === '%d' && r.dataset.name === %s);
  row.scrollIntoView({block: 'center'});
  const svg = row.querySelector('svg.spark');
  const box = svg.getBoundingClientRect();
  const [start, , width] = svg.getAttribute('viewBox').split(' ').map(Number);
  const xs = [...svg.querySelector('path.line').getAttribute('d').matchAll(/[ML]([-0-9.]+) /g)]
    .map(m => Math.min(box.right - 0.5, Math.max(box.left + 0.5,
      box.left + (Number(m[1]) - start) / width * box.width)));
  return JSON.stringify({first: xs[0], last: xs[xs.length - 1], y: box.top + box.height / 2});
})()""" % (json.dumps(DEMO_BUS), FREQUENCY_SLAVE, json.dumps(FREQUENCY))


def reads_under_pointer(browser):
    """With the page offline (its plots hold still), the mouse on drive 2's frequency plot: at its
    first reading the plot must read 0 Hz (the drive before the run command), at its last the
    reading shown in its row, each with its age, a dot on it; moved away, no reading. Returns
    what the plot read."""
    at = json.loads(browser.evaluate(PLOT_POINTS))
    read = []
    for x, what in ((at["first"], "first"), (at["last"], "last")):
        browser.mouse(x, at["y"])
        row = value_row(browser.wait_for(
            f"a reading under the mouse at drive {FREQUENCY_SLAVE}'s plot's {what} reading",
            lambda s: (value_row(s, FREQUENCY_SLAVE) or {}).get("pointing")), FREQUENCY_SLAVE)
        wanted = "0 Hz" if what == "first" else row["cells"][1]
        value, _, ago_text = row["pointer"].partition(", ")
        if value != wanted or age(ago_text) < 0 or not (row["dot"] or "").endswith("h0"):
            fail(f"the reading under the mouse at the {what} reading of drive {FREQUENCY_SLAVE}'s "
                 f"plot: wanted {wanted} and an age, and a dot", row)
        read.append(row["pointer"])
    browser.mouse(0, 0)
    browser.wait_for("no reading once the mouse left the plot",
                     lambda s: not value_row(s, FREQUENCY_SLAVE)["pointing"])
    return read


def shows_virtual_unit(snapshot):
    """The demo's unit 100: the four drives' frequencies, each from its drive, fresh once polled."""
    rows = snapshot["virtual"]
    return len(rows) == 4 and all(
        row[0] == "100 drives" and row[1] == f"holding {i}" and row[2] == "u16"
        and row[3] == f"demo/{i + 1}/drive_output_frequency_hertz" and row[6] == "fresh"
        for i, row in enumerate(rows))


def shows_demo(snapshot):
    buses = [b for b in snapshot["buses"] if b["bus"] == DEMO_BUS and "open" in b["text"]]
    drives = {s["slave"]: s["text"] for s in snapshot["slaves"] if s["bus"] == DEMO_BUS}
    return buses and all(
        address in drives and model in drives[address] for address, model in DEMO_DRIVES.items())


# Two registers each demo drive answers: the Goodrive state words, the Pd inverter's
# frequency reference and running frequency.
STATE_REGISTER = {1: 0x2100, 2: 0x2100, 3: 0x2100, 4: 0x1000}


def traffic(port, stop):
    """Two masters polling the drives until `stop` is set, for a screenshot with data in it."""
    def poll(units):
        master = Master(port)
        while not stop.is_set():
            for unit in units:
                master.read(unit, STATE_REGISTER[unit], 2)
            stop.wait(0.2)
        master.close()
    threads = [threading.Thread(target=poll, args=(units,)) for units in ((1, 2), (3, 4))]
    for thread in threads:
        thread.start()
    return threads


def main():
    metrics_port, modbus_port = int(sys.argv[1]), int(sys.argv[2])
    screenshot = sys.argv[4] if len(sys.argv) > 4 and sys.argv[3] == "--screenshot" else None
    log = open(os.environ.get("CHROMIUM_LOG", os.devnull), "ab")
    browser = Browser(log)
    try:
        browser.open(f"http://127.0.0.1:{metrics_port}/")
        browser.wait_for("the demo bus and its four drives", shows_demo)
        browser.wait_for("the live trace connected", lambda s: s["trace"] == "live")
        virtual = browser.wait_for("the demo's virtual unit 100, its four registers fresh",
                                   shows_virtual_unit)["virtual"]
        for call, wanted in PAGE_FUNCTIONS.items():
            got = browser.evaluate(call)
            if got != wanted:
                fail(f"the page's {call}", {"wanted": wanted, "got": got})
        # Sent after the page loaded and its trace connected: the panel must show it.
        master = Master(modbus_port)
        request = master.read(3, 0x2103, 1)
        frame = browser.wait_for(
            f"the request to drive 3 ({request}) in the trace panel",
            lambda s: any(f["direction"] == "tx" and f["slave"] == 3 and request in f["cells"]
                          for f in s["frames"]))
        browser.wait_for(
            f"the master {master.address()} among the connected masters",
            lambda s: master.address() in s["masters"])
        # The slave filter opens the trace again for that slave alone.
        browser.evaluate("""(() => {
          document.getElementById('trace-clear').click();
          const slave = document.getElementById('trace-slave');
          slave.value = '2';
          slave.dispatchEvent(new Event('change'));
        })()""")
        browser.wait_for("the trace open again for slave 2", lambda s: s["trace"] == "live")
        master.read(1, 0x2103, 1)
        wanted = master.read(2, 0x2103, 1)
        filtered = browser.wait_for(
            f"the request to drive 2 ({wanted}) in the trace filtered for slave 2",
            lambda s: any(wanted in f["cells"] for f in s["frames"]))
        others = [f for f in filtered["frames"] if f["slave"] != 2]
        if others:
            fail("frames of other slaves in the trace filtered for slave 2", others)
        master.close()
        browser.wait_for("no writes yet in the last writes",
                         lambda s: [w["cells"] for w in s["writes"]] == [[NO_WRITES]])
        readings, points_before, points_after = follows_a_write(browser, modbus_port)
        scale = frequency(browser.wait_for(
            f"drive {FREQUENCY_SLAVE}'s plot from min 0 Hz to max its reading now, from at least "
            f"{PLOT_MIN_SECONDS} s ago to now", shows_scale))
        writes = shows_writes(browser, modbus_port)
        labelled = labelled_by_help(browser, metrics_port)
        failed = value_row(browser.wait_for(
            f"slave {FAILED_SLAVE}'s value marked: poll failed", marks_failed), FAILED_SLAVE)
        captions = [fits(browser, width) for width in WIDTHS][-1]
        browser.resize(1280)
        print("virtual unit: " + "; ".join(" | ".join(row) for row in virtual))
        print(f"status page in {CHROMIUM}: bus {DEMO_BUS}, drives {sorted(DEMO_DRIVES)}, "
              f"the frame {request} in the trace panel ({len(frame['frames'])} frames shown), "
              f"and with the slave filter only slave 2's; at "
              f"{', '.join(f'{w} px' for w in WIDTHS)} no sideways page scroll, {captions} "
              "captions, the writes' outcomes and the failed value's mark in full view")
        print("last writes, newest first: " + "; ".join(
            " | ".join(w["cells"][:RULE_ACTION + 1]) for w in writes))
        print(f"plant values: {labelled} labelled by their help text; after the run command, "
              f"drive {FREQUENCY_SLAVE}'s {FREQUENCY} (\"{FREQUENCY_HELP}\") shown "
              f"{' -> '.join(f'{r:g} Hz' for r in readings)}, its plot from {points_before} to "
              f"{points_after} readings, scaled \"{scale['max']}\", \"{scale['min']}\", "
              f"\"{scale['from']}\" to \"{scale['to']}\"; slave {FAILED_SLAVE}'s marked "
              f"\"{failed['mark']}\"")
        if screenshot:
            stop = threading.Event()
            threads = traffic(modbus_port, stop)
            try:
                browser.wait_for("the two polling masters", lambda s: s["masters"].count("tcp") == 2)
                time.sleep(4.5)  # two more polls of /status with the traffic in them
                browser.screenshot(screenshot)
            finally:
                stop.set()
                for thread in threads:
                    thread.join()
            print(f"screenshot: {screenshot}")
        # Last: the page loses the gateway. It must say so, and its ages must keep counting.
        browser.call("Network.enable")
        browser.call("Network.emulateNetworkConditions", {
            "offline": True, "latency": 0, "downloadThroughput": -1, "uploadThroughput": -1})
        lost = browser.wait_for(
            "that it cannot reach the gateway, and ages counting on (3 s or more)",
            lambda s: "Cannot reach the gateway" in s["problem"] and age(s["updated"]) >= 3
            and age(s["drive 3"]) >= 3 and age(frequency(s)["cells"][2]) >= 3)
        print(f"offline: \"updated {lost['updated']}\", drive 3's last answer {lost['drive 3']}, "
              f"drive {FREQUENCY_SLAVE}'s last frequency reading {frequency(lost)['cells'][2]}")
        read = reads_under_pointer(browser)
        print(f"under the mouse, drive {FREQUENCY_SLAVE}'s plot read: " + "; then ".join(read))
    finally:
        browser.close()


if __name__ == "__main__":
    main()

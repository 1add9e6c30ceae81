"use strict";
// Every value is put into the page as text (textContent), never as markup.
const POLL_MS = 2000;
// A gateway that accepts the connection and never answers counts as not answering after this.
const ANSWER_WITHIN_MS = 5000;
// Ages are redrawn this often between polls, so they keep counting when the gateway stops.
const TICK_MS = 1000;
const KEEP_FRAMES = 200;
// A plot spans at least this, so that a value's first readings do not fill its width.
const PLOT_MIN_SECONDS = 60;
// A silence of more than this many times a value's usual spacing between readings (polls that
// failed) breaks its plot's line.
const PLOT_GAP_FACTOR = 3;
const $ = (id) => document.getElementById(id);

function cell(text, className) {
  const td = document.createElement("td");
  td.textContent = text === null || text === undefined ? "–" : String(text);
  if (className) td.className = className;
  return td;
}

// Set `element`'s text only if it differs: most of the page is the same from one poll to the next.
function setText(element, text) {
  if (element.textContent !== text) element.textContent = text;
}

function row(cells, data) {
  const tr = document.createElement("tr");
  for (const c of cells) tr.appendChild(c instanceof Node ? c : cell(c));
  if (data) for (const [k, v] of Object.entries(data)) tr.dataset[k] = String(v);
  return tr;
}

function fill(tbody, rows, empty, columns) {
  if (rows.length === 0) {
    const td = cell(empty, "idle");
    td.colSpan = columns;
    rows = [row([td])];
  }
  tbody.replaceChildren(...rows);
}

function span(seconds) {
  if (seconds === null || seconds === undefined) return "–";
  const s = Math.floor(seconds);
  if (s < 60) return s + " s";
  if (s < 3600) return Math.floor(s / 60) + " min " + (s % 60) + " s";
  if (s < 86400) return Math.floor(s / 3600) + " h " + Math.floor((s % 3600) / 60) + " min";
  return Math.floor(s / 86400) + " d " + Math.floor((s % 86400) / 3600) + " h";
}

function ago(seconds) {
  if (seconds === null || seconds === undefined) return "never";
  return seconds < 1 ? "just now" : span(seconds) + " ago";
}

// When /status last answered, on the page's monotonic clock. An age shown is the gateway's own
// figure at that answer plus the time since on this clock, so neither a wrong clock in the browser
// nor its time zone changes it.
let answeredAt = null;
let failure = null;

function sinceAnswer() { return (performance.now() - answeredAt) / 1000; }

// An element showing an age: `seconds` ago at the last answer, the absolute UTC time as tooltip.
function aged(element, seconds, utc) {
  if (seconds === null || seconds === undefined) {
    delete element.dataset.age;
    element.textContent = ago(null);
  } else {
    element.dataset.age = String(seconds);
    setText(element, ago(seconds + (answeredAt === null ? 0 : sinceAnswer())));
  }
  if (utc) element.title = utc; else element.removeAttribute("title");
  return element;
}

function tick() {
  if (answeredAt === null) return;
  const elapsed = sinceAnswer();
  for (const element of document.querySelectorAll("[data-age]")) {
    setText(element, ago(Number(element.dataset.age) + elapsed));
  }
  if (failure) {
    $("problem").textContent = "Cannot reach the gateway (" + failure + "): its last answer was " +
      ago(elapsed) + "; the figures below are from then, and their ages keep counting.";
  }
}

function millis(seconds) {
  if (seconds === null || seconds === undefined) return "–";
  const ms = seconds * 1000;
  return (ms < 10 ? ms.toFixed(2) : ms < 100 ? ms.toFixed(1) : ms.toFixed(0)) + " ms";
}

function state(up, className) {
  const td = cell(up);
  td.className = className;
  return td;
}

function utilisation(share) {
  const td = document.createElement("td");
  const meter = document.createElement("meter");
  meter.min = 0; meter.max = 1; meter.low = 0.6; meter.high = 0.85; meter.optimum = 0;
  meter.value = share;
  const label = (share * 100).toFixed(1) + " %";
  meter.textContent = label;
  meter.setAttribute("aria-label", label);
  td.append(meter, " " + label);
  return td;
}

// A serial port is open or down; a device server's link is connected, with its round trip and
// what the gateway budgets for it, or not.
function port(b) {
  const network = b.transport === "tcp" || b.transport === "rfc2217";
  if (!b.port_up) return state(network ? "not connected" : "down", "down");
  if (!network || !b.link) return state("open", "up");
  const td = state("connected, round trip " + millis(b.link.round_trip_seconds) +
    " (budget " + millis(b.link.budget_seconds) + ")", "up");
  td.title = b.link.peer;
  return td;
}

function renderBuses(buses) {
  fill($("buses"), buses.map((b) => row([
    b.name, b.device,
    b.framing.toUpperCase() + ", " + b.format + (b.mode === "listen" ? ", listen-only" : ""),
    port(b),
    utilisation(b.utilisation),
    cell(b.queue_depth + " / " + b.queue_capacity, "num"),
    cell(b.transactions, "num"),
  ], { bus: b.name })), "no buses", 7);
  const select = $("trace-bus");
  const known = new Set([...select.options].map((o) => o.value));
  for (const b of buses) {
    if (!known.has(b.name)) {
      const option = document.createElement("option");
      option.value = b.name;
      option.textContent = b.name;
      select.appendChild(option);
    }
  }
}

function slaveState(s) {
  if (s.up) return state("answering", "up");
  const asked = s.polls > 0 || Object.values(s.requests).some((n) => n > 0);
  if (!asked && s.last_answer === null) return state("not asked yet", "idle");
  return state("not answering", "down");
}

function renderSlaves(buses) {
  const rows = [];
  for (const b of buses) {
    for (const s of b.slaves) {
      const total = Object.values(s.requests).reduce((a, n) => a + n, 0);
      const errors = cell(s.errors, "num");
      const kinds = Object.entries(s.requests).filter(([k, n]) => k !== "ok" && n > 0);
      if (kinds.length) errors.title = kinds.map(([k, n]) => k + ": " + n).join(", ");
      const last = aged(cell(null), s.last_answer_seconds_ago, s.last_answer);
      rows.push(row([b.name, cell(s.address, "num"), s.model ? "simulated " + s.model : "–",
        slaveState(s), last, cell(millis(s.round_trip_p50_seconds), "num"),
        cell(total, "num"), errors], { bus: b.name, slave: s.address }));
    }
  }
  fill($("slaves"), rows, "no slaves known yet", 8);
}

function renderMasters(masters) {
  fill($("masters"), masters.map((m) => row([
    m.address, m.protocol, m.rights, m.role, span(m.connected_seconds),
    cell(m.requests, "num"),
  ])), "no master connected", 6);
}

function renderPorts(ports) {
  fill($("ports"), ports.map((p) => row([
    p.name, p.device, p.format + " " + p.framing.toUpperCase(), p.up ? "open" : "not open",
    ...["answered", "exception", "broadcast", "not_addressed", "bad_frame", "too_late"]
      .map((k) => cell(p.requests[k], "num")),
  ])), "no serial master port configured", 10);
}

function renderVirtual(units) {
  const rows = units.flatMap((u) => u.registers.map((r) => {
    const state = cell(r.fresh ? "fresh" : "stale");
    state.className = r.fresh ? "up" : "down";
    return row([
      u.unit + " " + u.name,
      r.table + " " + r.register + (r.bit === undefined || r.bit === null ? "" : "." + r.bit)
        + (r.writable ? " (writable)" : ""),
      r.type,
      r.source || "not in its source",
      cell(r.value === null || r.value === undefined ? "\u2013" : String(r.value), "num"),
      cell(r.age_seconds === null || r.age_seconds === undefined ? "never read"
        : r.age_seconds.toFixed(1) + " s", "num"),
      state,
    ]);
  }));
  fill($("virtual"), rows, "no virtual unit configured", 7);
}

// The public function codes a write may carry, named as the Modbus Application Protocol names
// them; any other code shows in hex.
const FUNCTION_NAMES = new Map([
  [0x05, "Write Single Coil"], [0x06, "Write Single Register"], [0x08, "Diagnostics"],
  [0x0F, "Write Multiple Coils"], [0x10, "Write Multiple Registers"], [0x15, "Write File Record"],
  [0x16, "Mask Write Register"], [0x17, "Read/Write Multiple Registers"],
  [0x2B, "Encapsulated Interface Transport"],
]);
// Outcomes shown as a failure or a success; the others (acknowledged, broadcast, cancelled) are
// neither.
const OUTCOME_CLASSES = new Map([["answered", "up"], ["slave_exception", "down"],
  ["gateway_exception", "down"], ["denied", "down"], ["timeout", "down"]]);

// A journal time (RFC 3339, UTC, to the microsecond) as Unix ms: Date.parse is sure of
// milliseconds only.
function unixMs(time) { return Date.parse(String(time).replace(/(\.\d{3})\d+/, "$1")); }

// A data address as a rule's `registers` key takes it, e.g. 0x2000.
function address(n) { return "0x" + Number(n).toString(16).toUpperCase().padStart(4, "0"); }

function writeMaster(w) {
  const td = cell(w.master);
  const extra = document.createElement("span");
  extra.className = "muted";
  extra.textContent = " " + [w.protocol, w.role ? "role " + w.role : null, w.subject]
    .filter(Boolean).join(", ");
  td.append(extra);
  return td;
}

function writeFunction(code) {
  const name = FUNCTION_NAMES.get(code);
  const td = cell(name || hex2(code));
  if (name) td.title = "function " + hex2(code);
  return td;
}

function writeRegisters(w) {
  if (w.table === undefined || w.start === undefined) return "–";
  const count = w.count === undefined ? 1 : w.count;
  const first = w.table + " " + address(w.start);
  return count <= 1 ? first : first + "–" + address(w.start + count - 1) + " (" + count + ")";
}

// The values as on the wire, a register's two bytes together.
function writeValues(w) {
  const groups = String(w.values).match(w.table === "holding" ? /.{1,4}/g : /.{1,2}/g);
  return cell(groups ? groups.join(" ") : "–", "hex");
}

// How a write ended, and why in words: shown, not in a tooltip, so that a phone has it too.
function writeOutcome(o) {
  if (o === null || o === undefined) return cell("pending", "outcome idle");
  const exception = o.exception === undefined ? "" : ", exception " + hex2(o.exception);
  const className = OUTCOME_CLASSES.get(o.outcome);
  const td = cell(o.outcome + exception, className ? "outcome " + className : "outcome");
  if (o.carried_out === "maybe") {
    const note = document.createElement("span");
    note.className = "note";
    note.textContent = "may have been carried out";
    td.append(document.createElement("br"), note);
  }
  if (o.detail) {
    const why = document.createElement("span");
    why.className = "why";
    why.textContent = o.detail;
    td.append(why);
  }
  return td;
}

// The last writes as /status has them (newest last; each the journal's write and its outcome,
// null until it has one), shown newest first, at the gateway's time `now` (Unix ms): how each
// ended first, so that a narrow screen shows it before the table scrolls.
function renderWrites(writes, now) {
  fill($("writes"), [...writes].reverse().map(({ write: w, outcome }) => {
    const at = unixMs(w.time);
    const time = Number.isNaN(at) ? cell(w.time, "when") :
      aged(cell(null, "when"), Math.max(0, now - at) / 1000, w.time);
    const target = w.bus === null ? "no route" : w.bus + " / " + w.slave;
    return row([writeOutcome(outcome), time, w.unit + " → " + target, writeFunction(w.function),
      writeRegisters(w), writeValues(w), (w.rule ?? "no rule") + ": " + w.action,
      writeMaster(w)],
    { id: w.id, unit: w.unit, outcome: outcome ? outcome.outcome : "pending" });
  }), "no writes since the gateway started", 8);
}

// A number as people write it: integers whole, others to 7 significant digits (a scaled register
// is rarely exact in binary: 6.390000000000001 is 6.39), whole from ten million on.
function number(value) {
  if (Number.isInteger(value) || Math.abs(value) >= 1e7) return String(Math.round(value));
  return String(Number(value.toPrecision(7)));
}

function reading(value, unit) {
  if (value === null || value === undefined) return "–";
  return unit ? number(value) + " " + unit : number(value);
}

// Where `value` sits on a plot between `low` (100, the bottom) and `high` (0); 50 if they are one.
function plotY(value, low, high) {
  return high === low ? "50" : (100 * (high - value) / (high - low)).toFixed(2);
}

// The line of a plot of `history`, readings [[unix_ms, value], ...] oldest first, as an SVG path:
// x in seconds from the first reading, y from 0 (the highest reading) to 100 (the lowest), 50 if
// all are equal. One "M" or "L" per reading; a silence longer than PLOT_GAP_FACTOR times the
// median spacing (`step`, ms) starts a new piece ("M"), so that the plot shows no readings that
// were never made, and each piece starts with a dot ("h0", round caps) so that a lone reading
// shows.
function sparkline(history) {
  let low = Infinity;
  let high = -Infinity;
  for (const [, value] of history) {
    if (value < low) low = value;
    if (value > high) high = value;
  }
  const steps = [];
  for (let i = 1; i < history.length; i++) steps.push(history[i][0] - history[i - 1][0]);
  steps.sort((a, b) => a - b);
  const step = steps.length ? steps[steps.length >> 1] : Infinity;
  const gap = step * PLOT_GAP_FACTOR;
  const origin = history.length ? history[0][0] : 0;
  let path = "";
  let previous = null;
  for (const [t, value] of history) {
    const x = ((t - origin) / 1000).toFixed(3);
    const y = plotY(value, low, high);
    path += previous === null || t - previous > gap ? "M" + x + " " + y + "h0" : "L" + x + " " + y;
    previous = t;
  }
  return { path, low, high, step };
}

// The reading of `history` nearest to the time `t` (Unix ms), or null if none is within `reach`
// ms of it.
function nearest(history, t, reach) {
  let best = null;
  for (const reading of history) {
    if (best === null || Math.abs(reading[0] - t) < Math.abs(best[0] - t)) best = reading;
  }
  return best !== null && Math.abs(best[0] - t) <= reach ? best : null;
}

// The plant values: one table per slave, one row per value. Rows are made once and changed in
// place, their plot's line redrawn only when its readings change, so that hundreds of values
// cost a few text and attribute updates per poll. The tables are made again only when the list
// of values changes (a reload).
const VALUE_COLUMNS = [["Value", ""], ["Reading", "num col-reading"],
  ["Last good reading", "col-read"], ["Last poll", "col-poll"], ["Last minutes", "col-plot"]];
// A reading this many pixels from the pointer, or half a usual spacing, is under it.
const POINTER_REACH_PX = 6;
const valueRows = new Map();
let valueGroups = [];
let valueLayout = null;

// A value's row is made again when what it is changes: its name, or what its first cell shows.
function valueKey(v) { return JSON.stringify([v.bus, v.slave, v.name, v.help, v.labels]); }

// A value's first cell: what it is in words (its help), then its metric's name and labels in
// small type, unless they would say the same again.
function valueName(v) {
  const td = document.createElement("td");
  const help = document.createElement("span");
  help.className = "help";
  help.textContent = v.help || v.name;
  td.append(help);
  const labels = Object.entries(v.labels || {}).map(([k, x]) => k + "=" + x).join(", ");
  const metric = [help.textContent === v.name ? "" : v.name, labels].filter(Boolean).join(" ");
  if (metric) {
    const small = document.createElement("span");
    small.className = "metric";
    small.textContent = metric;
    td.append(small);
  }
  return td;
}

function valueRow(v) {
  const plot = $("plot").content.firstElementChild.cloneNode(true);
  const part = (selector) => plot.querySelector(selector);
  const r = { reading: cell(null, "num"), read: cell(null), outcome: cell(null), plot,
    svg: part("svg"), title: part("title"), path: part(".line"), cursor: part(".cursor"),
    dot: part(".dot"), high: part(".plot-max"), low: part(".plot-min"), from: part(".plot-from"),
    to: part(".plot-to"), pointed: part(".plot-pointer"), unit: v.unit, drawn: null, line: null,
    history: [], origin: 0, last: 0, left: 0, right: 0, now: 0, pointer: null };
  const point = (event) => {
    const box = r.svg.getBoundingClientRect();
    if (box.width <= 0) return;
    const at = Math.min(1, Math.max(0, (event.clientX - box.left) / box.width));
    r.pointer = { at, px: box.width };
    showPointer(r);
  };
  r.svg.addEventListener("pointermove", point);
  r.svg.addEventListener("pointerdown", point);
  r.svg.addEventListener("pointerleave", (event) => {
    // A finger lifted leaves its reading shown; a mouse that leaves takes it away.
    if (event.pointerType === "touch") return;
    r.pointer = null;
    showPointer(r);
  });
  const name = valueName(v);
  r.mark = document.createElement("span");
  r.mark.className = "failed-mark";
  name.firstChild.after(r.mark);
  const td = document.createElement("td");
  td.append(plot);
  r.tr = row([name, r.reading, r.read, r.outcome, td],
    { bus: v.bus, slave: v.slave, name: v.name });
  return r;
}

// Row `r`'s plot as pointed at, if it is: a line through the nearest reading within reach of
// the pointer, a dot on it, and its value and age in words in place of the time scale.
function showPointer(r) {
  const pointing = r.pointer !== null && r.history.length > 0;
  r.plot.classList.toggle("pointing", pointing);
  if (!pointing) {
    r.cursor.removeAttribute("d");
    r.dot.removeAttribute("d");
    setText(r.pointed, "");
    return;
  }
  const now = r.now + (answeredAt === null ? 0 : sinceAnswer() * 1000);
  const t = r.left + r.pointer.at * (r.right - r.left);
  const step = r.line.step === Infinity ? 0 : r.line.step / 2;
  const found = nearest(r.history, t, Math.max(step, (r.right - r.left) * POINTER_REACH_PX /
    r.pointer.px));
  const at = found === null ? t : found[0];
  const x = "M" + ((at - r.origin) / 1000).toFixed(3) + " ";
  r.cursor.setAttribute("d", x + "-4V104");
  if (found === null) {
    r.dot.removeAttribute("d");
    setText(r.pointed, "no reading, " + ago(Math.max(0, now - t) / 1000));
    return;
  }
  r.dot.setAttribute("d", x + plotY(found[1], r.line.low, r.line.high) + "h0");
  setText(r.pointed, reading(found[1], r.unit) + ", " + ago(Math.max(0, now - at) / 1000));
}

// Lay the values out anew: a group per slave, in the order of `values` (configuration order),
// its caption above its scroll box.
function layValues(values, keys) {
  const wanted = new Set(keys);
  for (const key of valueRows.keys()) if (!wanted.has(key)) valueRows.delete(key);
  const groups = new Map();
  values.forEach((v, i) => {
    if (!valueRows.has(keys[i])) valueRows.set(keys[i], valueRow(v));
    const group = v.bus + "\u0000" + v.slave;
    if (!groups.has(group)) groups.set(group, { bus: v.bus, slave: v.slave, rows: [] });
    groups.get(group).rows.push(valueRows.get(keys[i]).tr);
  });
  valueGroups = [...groups.values()].map((g, i) => {
    const caption = document.createElement("h3");
    caption.className = "caption";
    caption.id = "values-" + i;
    const head = document.createElement("tr");
    for (const [name, className] of VALUE_COLUMNS) {
      const th = document.createElement("th");
      th.scope = "col";
      th.textContent = name;
      th.className = className;
      head.append(th);
    }
    const thead = document.createElement("thead");
    thead.append(head);
    const tbody = document.createElement("tbody");
    tbody.append(...g.rows);
    const table = document.createElement("table");
    table.className = "values";
    table.setAttribute("aria-labelledby", caption.id);
    table.append(thead, tbody);
    const scroll = document.createElement("div");
    scroll.className = "wide";
    scroll.append(table);
    const box = document.createElement("div");
    box.className = "slave-values";
    box.dataset.bus = g.bus;
    box.dataset.slave = String(g.slave);
    box.append(caption, scroll);
    return { bus: g.bus, slave: g.slave, caption, box };
  });
  const boxes = valueGroups.map((g) => g.box);
  if (values.length === 0) {
    const none = document.createElement("p");
    none.className = "idle";
    none.textContent = "No plant values configured.";
    boxes.push(none);
  }
  $("values").replaceChildren(...boxes);
}

// Value `v`'s row `r` as of the gateway's time `now` (Unix ms). A value whose last poll failed
// says so in words under its name, in the colour of failures, with a bar down its row.
function showValue(r, v, now) {
  const failed = Boolean(v.error);
  setText(r.reading, reading(v.value, v.unit));
  setText(r.mark, failed ? "poll failed: " + v.error : "");
  const read = v.read_at === null ? null : Date.parse(v.read_at);
  aged(r.read, read === null ? null : Math.max(0, now - read) / 1000, v.read_at);
  const [outcome, className] = failed ? [v.error, "down"] :
    v.read_at === null ? ["not polled yet", "idle"] : ["ok", "up"];
  setText(r.outcome, outcome);
  r.outcome.className = className;
  r.tr.classList.toggle("failed", failed);
  r.tr.classList.toggle("stale", v.value === null);
  r.unit = v.unit;
  const history = v.history || [];
  const n = history.length;
  const drawn = n ? n + " " + history[0][0] + " " + history[n - 1][0] : "";
  if (drawn !== r.drawn) {
    r.drawn = drawn;
    r.history = history;
    r.line = sparkline(history);
    r.path.setAttribute("d", r.line.path);
    r.origin = n ? history[0][0] : now;
    r.last = n ? history[n - 1][0] : now;
    setText(r.high, n ? "max " + reading(r.line.high, v.unit) : "");
    setText(r.low, n ? "min " + reading(r.line.low, v.unit) : "");
    const summary = n === 0 ? "no good reading in the last 10 min" :
      n === 1 ? "1 reading: " + reading(r.line.low, v.unit) :
      n + " readings over " + span((r.last - r.origin) / 1000) + ", from " +
      reading(r.line.low, v.unit) + " to " + reading(r.line.high, v.unit);
    setText(r.title, summary);
    r.svg.setAttribute("aria-label", summary);
  }
  // From the oldest reading to now (on the gateway's clock), at least PLOT_MIN_SECONDS.
  r.now = now;
  r.right = Math.max(now, r.last);
  r.left = Math.min(r.origin, r.right - PLOT_MIN_SECONDS * 1000);
  const box = ((r.left - r.origin) / 1000).toFixed(1) + " -4 " +
    ((r.right - r.left) / 1000).toFixed(1) + " 108";
  if (r.svg.getAttribute("viewBox") !== box) r.svg.setAttribute("viewBox", box);
  setText(r.from, n ? ago((r.right - r.left) / 1000) : "no good reading in 10 min");
  setText(r.to, n ? "now" : "");
  showPointer(r);
}

// `values` as /values has them, the slaves' models from `buses`, at the gateway's time `now`.
function renderValues(values, buses, now) {
  const keys = values.map(valueKey);
  const layout = keys.join("\n");
  if (layout !== valueLayout) {
    layValues(values, keys);
    valueLayout = layout;
  }
  const models = new Map();
  for (const b of buses) {
    for (const s of b.slaves) models.set(b.name + "\u0000" + s.address, s.model);
  }
  for (const g of valueGroups) {
    const model = models.get(g.bus + "\u0000" + g.slave);
    setText(g.caption, "Bus " + g.bus + ", slave " + g.slave +
      (model ? " (simulated " + model + ")" : ""));
  }
  values.forEach((v, i) => showValue(valueRows.get(keys[i]), v, now));
}

async function fetchJson(url) {
  const response = await fetch(url,
    { cache: "no-store", signal: AbortSignal.timeout(ANSWER_WITHIN_MS) });
  if (!response.ok) throw new Error("HTTP " + response.status + " from " + url);
  return response.json();
}

async function poll() {
  try {
    const [s, v] = await Promise.all([fetchJson("status"), fetchJson("values?history=1")]);
    $("version").textContent = "version " + s.version;
    $("uptime").textContent = span(s.uptime_seconds);
    answeredAt = performance.now();
    failure = null;
    aged($("updated"), 0, s.time);
    renderBuses(s.buses);
    renderSlaves(s.buses);
    renderMasters(s.masters);
    renderPorts(s.serial_ports || []);
    renderVirtual(s.virtual_units || []);
    renderWrites(s.writes || [], Date.parse(s.time));
    renderValues(v.values, s.buses, Date.parse(s.time));
    $("problem").textContent = "";
  } catch (error) {
    failure = error.message;
    if (answeredAt === null) {
      $("problem").textContent = "Cannot reach the gateway (" + failure + "); it has not answered yet.";
    }
    tick();
  } finally {
    setTimeout(poll, POLL_MS);
  }
}

// The live trace: one EventSource, opened again whenever a filter changes.
let source = null;
let lost = 0;
let paused = false;
let held = 0;

function traceState(text) { $("trace-state").textContent = text; }

function showLost() {
  const parts = [];
  if (lost) parts.push(lost + " frames lost (the trace fell behind)");
  if (held) parts.push(held + " frames not shown while paused");
  $("trace-lost").textContent = parts.join("; ");
}

function hex2(n) { return "0x" + Number(n).toString(16).padStart(2, "0").toUpperCase(); }

function addFrame(f) {
  if (paused) { held += 1; showLost(); return; }
  const tx = f.direction === "tx";
  const time = typeof f.time === "string" ? f.time.replace(/^.*T/, "").replace(/Z$/, "") : "";
  const tr = row([time, f.bus, cell(tx ? "→ to slave" : "← from slave", tx ? "tx" : ""),
    cell(f.slave, "num"), hex2(f.function), cell(f.hex, "hex"),
    cell(f.outcome, f.outcome === "ok" ? "up" : "down")],
    { direction: f.direction, slave: f.slave, bus: f.bus });
  const tbody = $("trace");
  tbody.prepend(tr);
  while (tbody.rows.length > KEEP_FRAMES) tbody.deleteRow(-1);
}

function connectTrace() {
  if (source) source.close();
  source = null;
  const slave = $("trace-slave");
  if (!slave.checkValidity()) { traceState("slave must be a number from 0 to 255"); return; }
  const query = new URLSearchParams();
  if ($("trace-bus").value) query.set("bus", $("trace-bus").value);
  if (slave.value !== "") query.set("slave", slave.value);
  const url = "trace" + (query.toString() ? "?" + query : "");
  traceState("connecting");
  source = new EventSource(url);
  source.onopen = () => traceState("live");
  source.onerror = () => traceState(source.readyState === EventSource.CLOSED ?
    "trace unavailable" : "reconnecting");
  source.addEventListener("frame", (event) => {
    try { addFrame(JSON.parse(event.data)); } catch (error) { /* not a frame */ }
  });
  source.addEventListener("lost", (event) => {
    try { lost += Number(JSON.parse(event.data).lost) || 0; } catch (error) { return; }
    showLost();
  });
}

$("trace-bus").addEventListener("change", connectTrace);
$("trace-slave").addEventListener("change", connectTrace);
$("trace-clear").addEventListener("click", () => {
  $("trace").replaceChildren();
  lost = 0; held = 0; showLost();
});
$("trace-pause").addEventListener("click", (event) => {
  paused = !paused;
  event.target.textContent = paused ? "Resume" : "Pause";
  event.target.setAttribute("aria-pressed", String(paused));
  if (!paused) { held = 0; showLost(); }
});

poll();
setInterval(tick, TICK_MS);
connectTrace();

// npp dashboard: follows /events (server-sent events) and draws the run. No libraries, nothing from outside.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
let state = { episodes: [], certificate: null, nodes: null, health: {}, plant: null, source: "", mode: "live" };
let connected = false;
let pending = false;

const $ = (id) => document.getElementById(id);
const num = (v) => (v === "inf" ? Infinity : v === "-inf" ? -Infinity : v === null ? NaN : Number(v));

function fmt(v, digits = 2) {
  const x = num(v);
  if (Number.isNaN(x)) return "-";
  if (!Number.isFinite(x)) return x > 0 ? "\u221e" : "-\u221e";
  if (Math.abs(x) >= 1e5) return x.toExponential(2);
  return x.toFixed(digits);
}
const int = (v) => Number(v).toLocaleString("en-US");

function el(tag, attrs = {}, text) {
  const node = document.createElementNS(tag === "svg" || attrs.svg ? SVG : "http://www.w3.org/1999/xhtml", tag);
  for (const [k, v] of Object.entries(attrs)) if (k !== "svg") node.setAttribute(k, v);
  if (text !== undefined) node.textContent = text;
  return node;
}
const svgEl = (tag, attrs, text) => el(tag, { ...attrs, svg: true }, text);

function render() {
  pending = false;
  const eps = state.episodes;
  const last = eps[eps.length - 1];
  const cert = state.certificate;
  document.body.dataset.episodes = String(eps.length);
  document.body.dataset.certified = String(Boolean(cert));

  if (state.plant) $("plant").textContent = `${state.plant.task} \u00b7 seed ${state.plant.seed} \u00b7 H = ${state.plant.horizon}`;
  $("source").textContent = state.source;
  const status = $("status");
  if (cert) { status.textContent = "certified"; status.className = "pill certified"; }
  else if (state.mode !== "live") { status.textContent = "finished, not certified"; status.className = "pill done"; }
  else if (!connected) { status.textContent = "disconnected"; status.className = "pill lost"; }
  else { status.textContent = "live"; status.className = "pill live"; }

  if (last) {
    $("episode").textContent = int(last.episode + 1);
    $("test").textContent = last.test ? `test ${last.test}` : "no policy under test yet";
    $("checked").textContent = fmt(last.checked_gap);
    $("epsilon").textContent = `epsilon ${fmt(last.epsilon, 0)} \u00b7 bounds gap ${fmt(last.gap)}`;
    $("streak").textContent = `${last.quiet} / ${last.required}`;
    const share = last.required ? Math.min(1, last.quiet / last.required) : 0;
    $("streak-bar").style.width = `${(share * 100).toFixed(1)}%`;
    $("streak-bar").className = share >= 1 ? "full" : "";
    $("dataset").textContent = int(last.dataset_size);
    $("oracle").textContent = int(last.oracle_calls);
    $("oracle-share").textContent = `${((100 * last.oracle_calls) / eps.length).toFixed(0)}% of episodes`;
    $("certify").textContent = last.certify ? `(${last.certify})` : "";
  }
  drawPlot();
  drawCertificate();
  drawNodes();
}

function schedule() {
  if (!pending) { pending = true; requestAnimationFrame(render); }
}

// Symmetric log: keeps negative gaps and gaps of 10^4 on one readable axis.
const symlog = (v) => Math.sign(v) * Math.log10(1 + Math.abs(v));

function drawPlot() {
  const svg = $("plot");
  const W = Math.max(svg.clientWidth, 300), H = Math.max(svg.clientHeight, 200);
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  svg.replaceChildren();
  const m = { l: 56, r: 16, t: 18, b: 30 };
  const eps = state.episodes;
  const epsilon = eps.length ? num(eps[eps.length - 1].epsilon) : NaN;
  const finite = eps.map((e) => num(e.checked_gap)).filter(Number.isFinite);
  if (Number.isFinite(epsilon)) finite.push(epsilon);
  // All gaps positive: start the axis at the decade below the smallest, not at 0.
  const smallest = finite.length ? Math.min(...finite) : 0;
  let lo = smallest > 0 ? symlog(10 ** Math.floor(Math.log10(Math.max(smallest, 1)))) : symlog(Math.min(0, smallest));
  let hi = Math.max(lo + 1, ...finite.map(symlog));
  hi += 0.08 * (hi - lo);
  const n = Math.max(eps.length ? eps[eps.length - 1].episode + 1 : 0, 10);
  const x = (k) => m.l + ((W - m.l - m.r) * k) / Math.max(n - 1, 1);
  const y = (v) => m.t + (H - m.t - m.b) * (1 - (symlog(v) - lo) / (hi - lo));
  const top = m.t - 8;

  // Grid and y ticks at 0, +-1, +-10, ...
  for (let p = 0; p <= 7; p++) {
    for (const s of p === 0 ? [0] : [1, -1]) {
      const v = p === 0 ? 0 : s * 10 ** (p - 1);
      const sv = symlog(v);
      if (sv < lo || sv > hi) continue;
      svg.append(svgEl("line", { class: "grid", x1: m.l, x2: W - m.r, y1: y(v), y2: y(v) }));
      const label = Math.abs(v) >= 1000 ? `${s < 0 ? "-" : ""}1e${p - 1}` : String(v);
      svg.append(svgEl("text", { x: m.l - 6, y: y(v) + 4, "text-anchor": "end" }, label));
    }
  }
  svg.append(svgEl("text", { x: m.l - 6, y: top + 4, "text-anchor": "end" }, "\u221e"));
  // x ticks
  const step = [1, 2, 5, 10, 20, 25, 50, 100, 200, 250, 500, 1000].find((s) => n / s <= 10) || 1000;
  for (let k = 0; k < n; k += step) {
    if (x(k) > W - m.r - 60) break; // keep clear of the axis label
    svg.append(svgEl("text", { x: x(k), y: H - 10, "text-anchor": "middle" }, String(k)));
  }
  svg.append(svgEl("line", { class: "axis", x1: m.l, x2: W - m.r, y1: H - m.b, y2: H - m.b }));
  svg.append(svgEl("text", { x: W - m.r, y: H - 10, "text-anchor": "end" }, "episode"));

  if (Number.isFinite(epsilon)) {
    svg.append(svgEl("line", { class: "eps", x1: m.l, x2: W - m.r, y1: y(epsilon), y2: y(epsilon) }));
    svg.append(svgEl("text", { class: "eps-label", x: W - m.r - 4, y: y(epsilon) - 5, "text-anchor": "end" },
      `\u03b5 = ${fmt(epsilon, 0)}`));
  }
  const cert = state.certificate;
  if (cert && cert.episodes) {
    const cx = x(cert.episodes - 1);
    svg.append(svgEl("line", { class: "cert", x1: cx, x2: cx, y1: m.t, y2: H - m.b }));
    svg.append(svgEl("text", { class: "cert-label", x: cx - 4, y: m.t + 10, "text-anchor": "end" }, "certified"));
  }

  const pts = eps.map((e) => {
    const v = num(e.checked_gap);
    return { e, px: x(e.episode), py: Number.isFinite(v) ? y(v) : v > 0 ? top : H - m.b, v };
  });
  if (pts.length > 1) {
    svg.append(svgEl("polyline", { class: "trace", points: pts.map((p) => `${p.px},${p.py}`).join(" ") }));
  }
  const r = pts.length > 400 ? 2 : 3;
  for (const p of pts) {
    const cls = p.e.oracle_called ? "oracle" : p.v <= num(p.e.epsilon) ? "quiet" : "over";
    const dot = svgEl("circle", { class: cls, cx: p.px, cy: p.py, r });
    dot.append(svgEl("title", {}, `episode ${p.e.episode}: checked gap ${fmt(p.e.checked_gap)}` +
      `${p.e.oracle_called ? " (oracle called)" : ""}, streak ${p.e.quiet}/${p.e.required}`));
    svg.append(dot);
  }
}

function drawCertificate() {
  const box = $("certificate");
  const cert = state.certificate;
  box.replaceChildren();
  if (!cert) {
    const last = state.episodes[state.episodes.length - 1];
    box.className = "pending";
    box.textContent = last
      ? `No certificate yet: the current test needs ${last.required} passed checks in a row (${last.quiet} so far).`
      : "No certificate yet.";
    return;
  }
  box.className = cert.proven === false ? "issued unproven" : "issued";
  box.append(el("div", { class: "statement" }, cert.statement || ""));
  const dl = el("dl");
  const rows = [
    ["proven", null],
    ["certifies", `${cert.certify || "-"}${cert.quantity ? ": " + cert.quantity : ""}`],
    ["test", cert.test ? `test ${cert.test}` : "-"],
    ["delta spent", cert.delta_spent !== null && cert.delta_spent !== undefined ? fmt(cert.delta_spent, 4) : "-"],
    ["epsilon, p, delta", `${fmt(cert.epsilon, 0)}, ${fmt(cert.p, 2)}, ${fmt(cert.delta, 2)}`],
    ["L", `${fmt(cert.lipschitz, 1)} (${cert.lipschitz_source || "-"})`],
    ["at", `episode ${cert.episodes}, ${int(cert.oracle_calls || 0)} oracle calls, |D| ${int(cert.dataset_size || 0)}`],
  ];
  for (const [k, v] of rows) {
    dl.append(el("dt", {}, k));
    const dd = el("dd");
    if (k === "proven") {
      dd.append(el("span", { class: `badge ${cert.proven ? "yes" : "no"}` }, cert.proven ? "yes" : "no: see assumptions"));
    } else dd.textContent = v;
    dl.append(dd);
  }
  box.append(dl);
  if (cert.assumptions && cert.assumptions.length) {
    box.append(el("div", { class: "muted" }, "Assumptions"));
    const ul = el("ul");
    for (const a of cert.assumptions) ul.append(el("li", {}, a));
    box.append(ul);
  }
}

function drawNodes() {
  const list = $("nodes");
  list.replaceChildren();
  if (!state.nodes) {
    list.append(el("li", { class: "muted" }, state.mode === "live" ? "looking at the graph\u2026" :
      `not live: showing a ${state.mode === "bag" ? "bag" : "run folder"}`));
    return;
  }
  for (const n of state.nodes) {
    const health = n.alive ? (state.health || {})[n.name] : undefined;
    const level = health ? health.level.toLowerCase() : "";
    const li = el("li", { class: `${n.alive ? "alive" : "gone"} ${level}`.trim() });
    li.append(el("span", { class: "state" }), el("span", {}, n.name),
      el("span", { class: "role" }, n.alive ? (n.role === "graph" ? "alive" : "alive (tool)") : "not running"));
    list.append(li);
    if (health) {
      const text = health.level === "OK" ? health.doing : `${health.level}: ${health.doing}` +
        (health.error ? ` (last error: ${health.error})` : "");
      list.append(el("li", { class: `health ${level}` }, text));
    }
  }
}

function connect() {
  const source = new EventSource("/events");
  source.addEventListener("open", () => { connected = true; schedule(); });
  source.addEventListener("error", () => { connected = false; schedule(); });
  source.addEventListener("snapshot", (ev) => { state = JSON.parse(ev.data); schedule(); });
  source.addEventListener("episode", (ev) => { state.episodes.push(JSON.parse(ev.data)); schedule(); });
  for (const key of ["certificate", "nodes", "health", "plant"]) {
    source.addEventListener(key, (ev) => { state[key] = JSON.parse(ev.data); schedule(); });
  }
}

window.addEventListener("resize", schedule);
connect();
render();

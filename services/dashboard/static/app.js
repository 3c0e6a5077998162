// AESOP dashboard: the service's /ws stream drawn on canvases. No libraries, no network
// beyond this origin. The first message on /ws is a snapshot; every later one is an item
// {kind, topic, received, message[, label]} (see services/dashboard/model.py).
"use strict";

(() => {
  const LIMITS = { trail: 3000, scores: 600, log: 50 };
  const css = getComputedStyle(document.documentElement);
  const color = (name) => css.getPropertyValue(`--${name}`).trim();
  const $ = (id) => document.getElementById(id);

  let flight = emptyFlight();
  let dirty = true;

  function emptyFlight() {
    return { robot: "", state: null, trail: [], plan: null, regions: [], goal: null,
             verdict: null, scores: [], requests: [], decisions: [], events: [], proposals: [],
             drift: null, services: {} };
  }

  // ---- the stream -------------------------------------------------------------------------

  let retryMs = 500;

  function connect() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const ws = new WebSocket(`${scheme}://${location.host}/ws`);
    setStatus("connecting");
    ws.onmessage = (event) => {
      apply(JSON.parse(event.data));
      dirty = true;
    };
    ws.onclose = (event) => {
      // 1008: refused (no token): open the address `aesop up` printed, with ?token=
      setStatus(event.code === 1008 ? "unauthorized: open /?token=<token>" : "disconnected");
      setTimeout(connect, retryMs);
      retryMs = Math.min(retryMs * 2, 5000);
    };
  }

  function setStatus(state) {
    const el = $("status");
    el.dataset.state = state;
    el.textContent = state;
  }

  function push(list, item, limit) {
    list.push(item);
    if (list.length > limit) list.splice(0, list.length - limit);
  }

  function apply(item) {
    const m = item.message;
    switch (item.kind) {
      case "snapshot":
        flight = Object.assign(emptyFlight(), m);
        retryMs = 500;
        setStatus("connected");
        $("logout").hidden = !flight.review_token;  // a token: this page reads by a session
        break;
      case "state": {
        const last = flight.trail[flight.trail.length - 1];
        if (last && m.t !== null && m.t < last[0]) flight.trail = [];  // the flight restarted
        const point = [m.t, m.x[0], m.x[1], m.x[2]];
        if (!point.includes(null)) push(flight.trail, [...point, m.mode], LIMITS.trail);
        flight.state = m;
        break;
      }
      case "plan": flight.plan = m; break;
      case "anomaly":
        flight.verdict = m;
        push(flight.scores, { seq: m.seq, stamp: m.stamp, score: m.score,
                              threshold: m.threshold, is_anomaly: m.is_anomaly }, LIMITS.scores);
        break;
      case "request": push(flight.requests, m, LIMITS.log); break;
      case "decision": push(flight.decisions, { ...m, label: item.label }, LIMITS.log); break;
      case "event":
        push(flight.events, m, LIMITS.log);
        if (m.source === "embedding" && m.kind.startsWith("proposal_") && m.data && m.data.id) {
          flight.proposals = flight.proposals.filter((p) => p.id !== m.data.id);
          push(flight.proposals, { ...m.data, stamp: m.stamp }, LIMITS.log);
        }
        if (m.source === "embedding" && (m.kind === "drift" || m.kind === "drift_cleared")) {
          flight.drift = m.kind === "drift" ? { message: m.message, data: m.data || {},
                                                stamp: m.stamp } : null;
        }
        break;
      case "health": flight.services[m.service] = m.alive; break;
      case "regions": flight.regions = m.regions; flight.goal = m.goal || flight.goal; break;
    }
  }

  // ---- header, lists ----------------------------------------------------------------------

  function renderHeader() {
    const s = flight.state;
    $("robot").textContent = flight.robot || "–";
    $("clock").textContent = s && Number.isFinite(s.t) ? `${s.t.toFixed(1)} s` : "–";
    const mode = $("mode");
    mode.dataset.mode = s ? s.mode : "";
    mode.textContent = !s ? "no state yet"
      : s.mode === "recovering" ? `recovering → y=${s.chosen}`
      : s.mode === "waiting" ? "waiting for the detector" : s.mode.replace("_", " ");
    const v = flight.verdict;
    const verdict = $("verdict");
    verdict.dataset.anomaly = v ? String(v.is_anomaly) : "";
    const named = !v || !v.is_anomaly ? ""
      : v.detections && v.detections.length ? ` · ${v.detections[0].detection}`
      : v.pair ? ` · ${v.pair.detections[0]} + ${v.pair.detections[1]}` : "";
    verdict.textContent = !v ? "no verdict yet"
      : `${v.is_anomaly ? "ANOMALY" : "nominal"} s=${v.score.toFixed(3)} τ=${
          v.threshold === null ? "none" : v.threshold.toFixed(3)}${
          v.p_value === null || v.p_value === undefined ? "" : ` p=${v.p_value.toFixed(3)}`}${named}`;
    const drift = $("drift");  // the detector flags more than its calibration allows
    drift.hidden = !flight.drift;
    drift.dataset.drift = String(Boolean(flight.drift));
    drift.textContent = !flight.drift ? "" : `DRIFT: new wording? ${
      flight.drift.data.flagged}/${flight.drift.data.seen} flagged${
      flight.drift.data.phrases ? " · " + flight.drift.data.phrases : ""}`;
    drift.title = flight.drift ? flight.drift.message : "";
    const services = $("services");
    services.replaceChildren(...Object.entries(flight.services).sort().map(([name, alive]) => {
      const el = document.createElement("span");
      el.className = "badge";
      el.dataset.service = name;
      el.dataset.alive = String(alive);
      el.textContent = name;
      el.title = alive ? `${name}: alive` : `${name}: gone`;
      return el;
    }));
  }

  function decisionFor(requestId) {
    return flight.decisions.find((d) => d.request_id === requestId);
  }

  function unusualLine(what, match) {
    const line = document.createElement("div");
    line.className = "unusual";
    line.textContent = `${what}, ${match.similarity.toFixed(2)}${
      match.p_value === null || match.p_value === undefined
        ? "" : ` (p ${match.p_value.toFixed(3)})`}`;
    return line;
  }

  function renderRequests() {
    const items = flight.requests.slice().reverse().map((r) => {
      const li = document.createElement("li");
      li.dataset.requestId = r.request_id;
      li.dataset.deadline = String(r.stamp + r.deadline_s);
      const countdown = document.createElement("span");
      countdown.className = "countdown";
      const text = document.createElement("div");
      text.textContent = `“${r.observation.text}”`;
      // what the detector named: each odd detection beside its nearest nominal one, and
      // the pair of detections no nominal experience holds together, if it named one
      const p = r.unusual_pair;
      const unusual = (r.unusual || []).map((m) =>
        unusualLine(`${m.detection} — nearest nominal: ${m.nearest}`, m));
      if (p) {
        unusual.push(unusualLine(`${p.detections[0]} together with ${p.detections[1]} — ` +
          `nearest nominal pair: ${p.nearest[0]} with ${p.nearest[1]}`, p));
      }
      const meta = document.createElement("div");
      meta.className = "meta";
      meta.textContent = `${clockOf(r.stamp)} · K=${r.deadline_s.toFixed(2)} s · ` +
        r.options.map((o) => `${o.index} ${o.label}`).join(" | ");
      li.append(countdown, text, ...unusual, meta);
      return li;
    });
    $("requests").replaceChildren(...items);
    tickCountdowns();
  }

  function tickCountdowns() {
    const now = Date.now() / 1000;
    for (const li of $("requests").children) {
      const decision = decisionFor(li.dataset.requestId);
      const left = Number(li.dataset.deadline) - now;
      const countdown = li.querySelector(".countdown");
      if (decision) {
        li.dataset.status = "answered";
        countdown.textContent = `y=${decision.choice} (${decision.source})`;
      } else if (left > 0) {
        li.dataset.status = "pending";
        countdown.textContent = `K in ${left.toFixed(1)} s`;
      } else {
        li.dataset.status = "expired";
        countdown.textContent = "past K";
      }
    }
  }

  function renderDecisions() {
    const items = flight.decisions.slice().reverse().map((d) => {
      const li = document.createElement("li");
      li.dataset.source = d.source;
      li.dataset.choice = String(d.choice);
      const choice = document.createElement("span");
      choice.className = "choice";
      choice.textContent = `y=${d.choice} ${d.label || (d.choice === 0 ? "continue" : "")}`;
      const source = document.createElement("span");
      source.className = "source";
      source.dataset.source = d.source;
      source.textContent = d.source;
      const meta = document.createElement("div");
      meta.className = "meta";
      meta.textContent = `${clockOf(d.stamp)} · ${d.latency_ms.toFixed(0)} ms` +
        (d.model ? ` · ${d.model}` : "") + (d.rationale ? ` · ${d.rationale}` : "") +
        (d.source !== "llm" && d.answer ? ` · the model wrote: ${d.answer}` : "");
      li.append(choice, source, meta);
      return li;
    });
    $("decisions").replaceChildren(...items);
  }

  function renderProposals() {
    // scenes the LLM answered "continue" for, proposed to the detector's cache; a pending
    // one has a box to select it for a batch review
    const items = flight.proposals.slice().reverse().map((p) => {
      const li = document.createElement("li");
      li.dataset.state = p.state;
      li.dataset.id = p.id;
      if (p.state === "pending") {
        const box = document.createElement("input");
        box.type = "checkbox";
        box.checked = selected.has(p.id);
        box.setAttribute("aria-label", "select for review");
        box.onchange = () => { if (box.checked) selected.set(p.id, p.cache);
                               else selected.delete(p.id); renderReview(); };
        li.append(box);
      } else {
        selected.delete(p.id);
      }
      const state = document.createElement("span");
      state.className = "state";
      state.textContent = p.state;
      const text = document.createElement("div");
      text.textContent = `“${p.text.split("\n").join(" / ")}”`;
      const meta = document.createElement("div");
      meta.className = "meta";
      meta.textContent = `${clockOf(p.stamp)} · ${p.cache} · proposed ${p.count}× · ${p.model}`;
      li.append(state, text, meta);
      return li;
    });
    $("proposals").replaceChildren(...items);
    renderReview();
  }

  // ---- batch review: the one write; the admin token is asked for when the dashboard
  // wants it, kept in this page's memory only, and sent as a bearer header (never a cookie)

  const selected = new Map();  // proposal id -> its cache
  let adminToken = null;

  function renderReview() {
    $("accept-selected").disabled = $("reject-selected").disabled = selected.size === 0;
  }

  async function review(decision) {
    const byCache = new Map();
    for (const [id, cache] of selected) {
      if (!byCache.has(cache)) byCache.set(cache, []);
      byCache.get(cache).push(id);
    }
    const said = [];
    if (flight.review_token && !adminToken) askToken();
    for (const [cache, ids] of byCache) {
      let answer = await send(decision, cache, ids);
      if (answer.status === 401 && askToken()) answer = await send(decision, cache, ids);
      const body = await answer.json().catch(() => ({}));
      if (answer.ok) {
        ids.forEach((id) => selected.delete(id));
        const cal = body.cache && body.cache.calibration;
        said.push(`${ids.length} ${decision === "accept" ? "accepted" : "rejected"} on ${cache}` +
                  (cal ? ` · calibration ${cal.method} on ${cal.n}${cal.stale ? " (stale)" : ""}` : ""));
      } else {
        said.push(`${cache}: ${answer.status} ${body.error ? body.error.message : ""}`);
      }
    }
    $("review-status").textContent = said.join("; ");
    renderReview();
  }

  function askToken() {
    adminToken = window.prompt("The admin token (AESOP_ADMIN_TOKEN), to review proposals:");
    return Boolean(adminToken);
  }

  function send(decision, cache, ids) {
    const headers = { "Content-Type": "application/json" };
    if (adminToken) headers.Authorization = `Bearer ${adminToken}`;
    return fetch(`/v1/proposals/${decision}`, {
      method: "POST", headers, body: JSON.stringify({ cache, ids }) });
  }

  // ---- the session: the cookie /?token= set names a session on the server; logging out
  // ends it there (another app on this host that got the cookie can replay it no more)
  $("logout").onclick = () => {
    fetch("/logout", { method: "POST" }).finally(() => location.replace("/"));
  };

  $("accept-selected").onclick = () => review("accept");
  $("reject-selected").onclick = () => review("reject");

  function renderEvents() {
    const items = flight.events.slice().reverse().map((e) => {
      const li = document.createElement("li");
      li.dataset.severity = e.severity;
      li.dataset.kind = e.kind;
      li.textContent = `${clockOf(e.stamp)} ${e.source}/${e.kind}${e.message ? ": " + e.message : ""}`;
      return li;
    });
    $("events").replaceChildren(...items);
  }

  function clockOf(stamp) {
    return new Date(stamp * 1000).toLocaleTimeString([], { hour12: false });
  }

  // ---- the top and side views ---------------------------------------------------------------

  function fitCanvas(canvas) {
    const ratio = window.devicePixelRatio || 1;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * ratio) || canvas.height !== Math.round(h * ratio)) {
      canvas.width = Math.round(w * ratio);
      canvas.height = Math.round(h * ratio);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, w, h);
    return { ctx, w, h };
  }

  function planBranches(plan) {
    // Every recovery branch shares its first K inputs: points 0..K are one prefix.
    if (!plan) return { prefix: [], branches: [] };
    const entries = Object.entries(plan.recovery || {})
      .map(([index, points]) => [Number(index), points]).sort((a, b) => a[0] - b[0]);
    if (!entries.length) return { prefix: [], branches: [] };
    const k = Math.min(plan.consensus_steps, entries[0][1].length - 1);
    return { prefix: entries[0][1].slice(0, k + 1),
             branches: entries.map(([index, points]) => ({ index, points: points.slice(k) })) };
  }

  // A view on two axes (0 = x, 1 = y, 2 = z) at equal scale.
  function drawView(canvas, a, b) {
    const { ctx, w, h } = fitCanvas(canvas);
    const s = flight.state, tree = planBranches(flight.plan);
    const pts = [];
    for (const r of flight.regions) pts.push(r.position_lo, r.position_hi);
    if (flight.goal) pts.push(flight.goal);
    for (const p of flight.trail) pts.push([p[1], p[2], p[3]]);
    if (flight.plan) pts.push(...flight.plan.nominal);
    for (const br of tree.branches) pts.push(...br.points);
    canvas.dataset.points = String(flight.trail.length);
    canvas.dataset.branches = String(tree.branches.length);
    canvas.dataset.regions = String(flight.regions.length);
    if (!pts.length) return empty(ctx, w, h, "waiting for the flight…");
    if (b === 2) pts.push([pts[0][0], 0, 0]);  // keep the ground in sight

    const pad = 28;
    let [amin, amax, bmin, bmax] = bounds(pts, a, b);
    const scale = Math.min((w - 2 * pad) / Math.max(amax - amin, 1), (h - 2 * pad) / Math.max(bmax - bmin, 1));
    const ac = (amin + amax) / 2, bc = (bmin + bmax) / 2;
    const X = (p) => w / 2 + (p[a] - ac) * scale;
    const Y = (p) => h / 2 - (p[b] - bc) * scale;

    grid(ctx, w, h, X, Y, a, b, ac, bc, scale);
    if (b === 2) line(ctx, [[-1e3, 0, 0], [1e3, 0, 0]], X, Y, color("dim"), 2);  // the ground

    const active = new Set(s ? s.active_regions : []);
    const labelled = new Map();  // label corner -> labels already there (boxes may coincide)
    for (const r of flight.regions) {
      const chosen = s && s.chosen === r.index;
      const x0 = X(r.position_lo), x1 = X(r.position_hi);
      const y0 = Y(r.position_hi), y1 = Y(r.position_lo);
      ctx.fillStyle = chosen ? color("chosen") : color("region");
      ctx.globalAlpha = chosen ? 0.45 : active.has(r.index) ? 0.35 : 0.18;
      ctx.fillRect(x0, y0, Math.max(x1 - x0, 2), Math.max(y1 - y0, 2));
      ctx.globalAlpha = 1;
      ctx.strokeStyle = chosen ? color("chosen") : color("region");
      ctx.lineWidth = active.has(r.index) || chosen ? 2 : 1;
      ctx.strokeRect(x0, y0, Math.max(x1 - x0, 2), Math.max(y1 - y0, 2));
      ctx.fillStyle = color("text");
      ctx.font = "11px system-ui, sans-serif";
      const corner = `${Math.round(x0)},${Math.round(y0)}`;
      const stacked = labelled.get(corner) || 0;
      labelled.set(corner, stacked + 1);
      ctx.fillText(`${r.index} ${r.label}`, x0 + 3, y0 - 4 - 13 * stacked);
    }

    if (flight.plan) line(ctx, flight.plan.nominal, X, Y, color("nominal"), 2);
    ctx.setLineDash([5, 4]);
    for (const br of tree.branches) {
      const chosen = s && s.chosen === br.index;
      line(ctx, br.points, X, Y, chosen ? color("chosen") : color("branch"), chosen ? 2.5 : 1.5);
      const end = br.points[br.points.length - 1];
      if (end) dot(ctx, X(end), Y(end), 3, chosen ? color("chosen") : color("branch"));
    }
    ctx.setLineDash([]);
    line(ctx, tree.prefix, X, Y, color("prefix"), 4);

    if (flight.goal) star(ctx, X(flight.goal), Y(flight.goal), color("goal"));
    const trail = flight.trail.map((p) => [p[1], p[2], p[3]]);
    line(ctx, trail, X, Y, color("trail"), 1.5);
    if (s) dot(ctx, X(s.x), Y(s.x), 6, s.mode === "nominal" ? color("ok") :
      s.mode === "recovering" ? color("chosen") : color("warn"), color("bg"));
  }

  function bounds(pts, a, b) {
    let amin = Infinity, amax = -Infinity, bmin = Infinity, bmax = -Infinity;
    for (const p of pts) {
      amin = Math.min(amin, p[a]); amax = Math.max(amax, p[a]);
      bmin = Math.min(bmin, p[b]); bmax = Math.max(bmax, p[b]);
    }
    const ma = 0.08 * (amax - amin) + 0.3, mb = 0.08 * (bmax - bmin) + 0.3;
    return [amin - ma, amax + ma, bmin - mb, bmax + mb];
  }

  function grid(ctx, w, h, X, Y, a, b, ac, bc, scale) {
    const step = niceStep(80 / scale);
    const names = ["x", "y", "z"];
    ctx.strokeStyle = color("line");
    ctx.fillStyle = color("dim");
    ctx.lineWidth = 1;
    ctx.font = "10px system-ui, sans-serif";
    const span = (c, px) => [Math.floor((c - px / scale) / step), Math.ceil((c + px / scale) / step)];
    const [i0, i1] = span(ac, w / 2), [j0, j1] = span(bc, h / 2);
    for (let i = i0; i <= i1; i++) {
      const p = [0, 0, 0]; p[a] = i * step;
      const x = X(p);
      ctx.beginPath(); ctx.moveTo(x, 0); ctx.lineTo(x, h); ctx.stroke();
      ctx.fillText(`${+(i * step).toFixed(2)}`, x + 2, h - 3);
    }
    for (let j = j0; j <= j1; j++) {
      const p = [0, 0, 0]; p[b] = j * step;
      const y = Y(p);
      ctx.beginPath(); ctx.moveTo(0, y); ctx.lineTo(w, y); ctx.stroke();
      ctx.fillText(`${+(j * step).toFixed(2)}`, 2, y - 2);
    }
    ctx.fillText(`${names[a]} →  ${names[b]} ↑`, w - 60, 12);
  }

  function niceStep(raw) {
    const mag = 10 ** Math.floor(Math.log10(raw));
    return [1, 2, 5, 10].map((f) => f * mag).find((s) => s >= raw);
  }

  function line(ctx, pts, X, Y, stroke, width) {
    if (!pts || pts.length < 2) return;
    ctx.strokeStyle = stroke;
    ctx.lineWidth = width;
    ctx.lineJoin = "round";
    ctx.beginPath();
    pts.forEach((p, i) => (i ? ctx.lineTo(X(p), Y(p)) : ctx.moveTo(X(p), Y(p))));
    ctx.stroke();
  }

  function dot(ctx, x, y, r, fill, stroke) {
    ctx.beginPath();
    ctx.arc(x, y, r, 0, 2 * Math.PI);
    ctx.fillStyle = fill;
    ctx.fill();
    if (stroke) { ctx.strokeStyle = stroke; ctx.lineWidth = 2; ctx.stroke(); }
  }

  function star(ctx, x, y, fill) {
    ctx.beginPath();
    for (let i = 0; i < 10; i++) {
      const r = i % 2 ? 3.5 : 8, t = -Math.PI / 2 + (i * Math.PI) / 5;
      ctx.lineTo(x + r * Math.cos(t), y + r * Math.sin(t));
    }
    ctx.closePath();
    ctx.fillStyle = fill;
    ctx.fill();
    ctx.fillStyle = color("text");
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillText("goal", x + 9, y + 4);
  }

  function empty(ctx, w, h, text) {
    ctx.fillStyle = color("dim");
    ctx.font = "13px system-ui, sans-serif";
    ctx.fillText(text, w / 2 - 60, h / 2);
  }

  // ---- the score timeline -----------------------------------------------------------------

  function drawScores(canvas) {
    const { ctx, w, h } = fitCanvas(canvas);
    const scores = flight.scores;
    const anomalies = scores.filter((s) => s.is_anomaly).length;
    canvas.dataset.points = String(scores.length);
    canvas.dataset.anomalies = String(anomalies);
    $("score-legend").textContent = scores.length
      ? `${scores.length} verdicts, ${anomalies} anomalies` : "";
    if (!scores.length) return empty(ctx, w, h, "waiting for verdicts…");

    const values = scores.flatMap((s) => (s.threshold === null ? [s.score] : [s.score, s.threshold]));
    let lo = Math.min(...values), hi = Math.max(...values);
    const margin = 0.1 * (hi - lo) + 0.01;
    lo -= margin; hi += margin;
    const t0 = scores[0].stamp, t1 = Math.max(scores[scores.length - 1].stamp, t0 + 1);
    const pad = { l: 48, r: 10, t: 8, b: 18 };
    const X = (t) => pad.l + ((t - t0) / (t1 - t0)) * (w - pad.l - pad.r);
    const Y = (v) => pad.t + ((hi - v) / (hi - lo)) * (h - pad.t - pad.b);

    ctx.strokeStyle = color("line");
    ctx.fillStyle = color("dim");
    ctx.font = "10px system-ui, sans-serif";
    for (const v of [lo + margin, (lo + hi) / 2, hi - margin]) {
      ctx.beginPath(); ctx.moveTo(pad.l, Y(v)); ctx.lineTo(w - pad.r, Y(v)); ctx.stroke();
      ctx.fillText(v.toFixed(3), 4, Y(v) + 3);
    }
    ctx.fillText(`${(t1 - t0).toFixed(0)} s`, w - pad.r - 24, h - 4);

    ctx.setLineDash([6, 4]);
    const withTau = scores.filter((s) => s.threshold !== null);
    line(ctx, withTau.map((s) => [X(s.stamp), Y(s.threshold)]), (p) => p[0], (p) => p[1],
         color("anomaly"), 1.5);
    ctx.setLineDash([]);
    line(ctx, scores.map((s) => [X(s.stamp), Y(s.score)]), (p) => p[0], (p) => p[1],
         color("nominal"), 1.5);
    for (const s of scores) {
      if (s.is_anomaly) dot(ctx, X(s.stamp), Y(s.score), 3.5, color("anomaly"));
    }
    if (withTau.length) {
      ctx.fillStyle = color("anomaly");
      ctx.fillText("τ", w - pad.r - 10, Y(withTau[withTau.length - 1].threshold) - 4);
    }
  }

  // ---- the render loop --------------------------------------------------------------------

  let shown = { requests: null, decisions: null, events: null, proposals: null };

  function render() {
    if (dirty) {
      dirty = false;
      renderHeader();
      drawView($("top"), 0, 1);
      drawView($("side"), 0, 2);
      drawScores($("score"));
      // lists are rebuilt only when they changed (they hold the countdowns)
      const keys = { requests: listKey(flight.requests), decisions: listKey(flight.decisions),
                     events: listKey(flight.events), proposals: listKey(flight.proposals) };
      if (keys.decisions !== shown.decisions) renderDecisions();
      if (keys.requests !== shown.requests || keys.decisions !== shown.decisions) renderRequests();
      if (keys.events !== shown.events) renderEvents();
      if (keys.proposals !== shown.proposals) renderProposals();
      shown = keys;
    }
    requestAnimationFrame(render);
  }

  function listKey(list) {
    const last = list[list.length - 1];
    return `${list.length}:${last ? last.stamp : ""}`;
  }

  // ---- the fleet overview (GET /v1/fleet, once a second) ---------------------------------

  let fleet = null;

  async function pollFleet() {
    try {
      const answer = await fetch("/v1/fleet", { cache: "no-store" });
      if (answer.ok) fleet = await answer.json();
    } catch (err) {
      // the service is away: the stream's status says so; the next poll tries again
    }
    renderFleet();
  }

  function cell(text, data) {
    const td = document.createElement("td");
    td.textContent = text;
    Object.assign(td.dataset, data || {});
    return td;
  }

  function renderFleet() {
    if (!fleet) return;
    $("fleet-robot").textContent = fleet.robot;
    const now = Date.now() / 1000;
    const rows = fleet.robots.map((r) => {
      const tr = document.createElement("tr");
      tr.dataset.robot = r.robot;
      tr.dataset.mine = String(r.robot === fleet.robot);
      const v = r.verdict;
      const verdict = v ? `${v.is_anomaly ? "ANOMALY" : "nominal"} (seq ${v.seq})` : "–";
      const p = r.pending;
      const left = p ? p.received + p.deadline_s - now : null;
      const waiting = p ? (left > 0 ? `K in ${left.toFixed(1)} s` : "past K") : "–";
      const d = r.decision;
      const decided = d ? `y=${d.choice} ${d.label || "?"} (${d.source})` : "–";
      const alarm = r.last_alarm ? `${r.alarms}: ${r.last_alarm.source}/${r.last_alarm.kind}` : "0";
      tr.replaceChildren(
        cell(r.robot), cell(r.mode || "–", { mode: r.mode || "" }),
        cell(verdict, { anomaly: String(Boolean(v && v.is_anomaly)) }),
        cell(waiting, { pending: String(Boolean(p)) }), cell(decided),
        cell(alarm, { alarms: String(r.alarms > 0) }),
        cell(`${Math.max(0, now - r.seen).toFixed(1)} s ago`));
      return tr;
    });
    $("fleet-rows").replaceChildren(...rows);
  }

  window.addEventListener("resize", () => { dirty = true; });
  setInterval(tickCountdowns, 100);
  setInterval(pollFleet, 1000);
  pollFleet();
  connect();
  requestAnimationFrame(render);
})();

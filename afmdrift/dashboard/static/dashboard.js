// afmdrift dashboard page: one WebSocket to the dashboard server, Plotly for the plots.
// The server sends a snapshot on connect, then deltas ("frames", "tick", "frame_view").
// Nothing is loaded from anywhere but the dashboard's own address.
"use strict";

(function () {
  const state = {
    frames: new Map(),        // seq -> row
    truth: [],                // [t_s, x_nm, y_nm]
    offset: null,             // envelope (see afmdrift/dashboard/_state.py envelope_json)
    channels: {},             // name -> envelope
    events: [],
    summary: null,
    view: null,
  };
  // Inspected by tests and the benchmark (tests/integration/test_dashboard.py).
  const probe = {
    connected: false, connects: 0, snapshots: 0, messages: 0,
    frameShown: {},           // seq -> Date.now() when its point was drawn
    latenciesMs: [],          // drawn − published (frame wall_s), frames first seen on the wire
    renders: {},              // plot id -> number of completed renders
    lastError: null,
    addTerm: null,            // the last "Add to model" answer: {status, body}
  };
  window.afmdriftDashboard = probe;

  const MAX_EVENTS_DRAWN = 300;
  const MAX_TRUTH_POINTS = 8000;   // afmdrift/dashboard/_state.py _TRUTH_CAP
  const MAX_LATENCIES = 10000;
  const PLOT_CONFIG = { displaylogo: false, responsive: true };
  const T_AXIS = { title: { text: "t (s, instrument clock)" }, zeroline: false };
  const COLORS = { x: "#1f77b4", y: "#d62728", truth: "#2ca02c", pred: "#9467bd", band: "rgba(148,103,189,0.18)" };

  function $(id) { return document.getElementById(id); }
  function fmt(v, d) { return v === null || v === undefined ? "–" : Number(v).toFixed(d === undefined ? 2 : d); }

  // ------------------------------------------------------------------ data

  function upsertFrames(rows) {
    const fresh = [];
    for (const row of rows) {
      const old = state.frames.get(row.seq);
      if (old === undefined) {
        state.frames.set(row.seq, row);
        if (!row.stored) fresh.push(row);
      } else {
        for (const k of Object.keys(row)) {
          if (row[k] !== null || !(k in old)) old[k] = row[k];
        }
      }
    }
    if (state.frames.size > 0) {
      const sorted = Array.from(state.frames.keys()).sort((a, b) => a - b);
      const max = (state.summary && state.summary.max_frames) || 5000;
      while (sorted.length > max) {
        const seq = sorted.shift();
        state.frames.delete(seq);
        delete probe.frameShown[seq];
      }
    }
    return fresh;
  }

  function mergeEnvelope(old, delta) {
    if (!old || old.generation !== delta.generation || delta.start === 0) return delta;
    const out = { generation: delta.generation, start: 0, width_s: delta.width_s };
    const cut = (arr, add) => arr.slice(0, delta.start).concat(add);
    out.t_s = cut(old.t_s, delta.t_s);
    out.count = cut(old.count, delta.count);
    for (const key of ["min", "max", "last", "flags"]) {
      out[key] = old[key].map((comp, j) => cut(comp, delta[key][j]));
    }
    return out;
  }

  function sortedFrames() {
    return Array.from(state.frames.values()).sort((a, b) => a.seq - b.seq);
  }

  // ------------------------------------------------------------------ plots

  function render(id, data, layout) {
    const div = $(id);
    return Plotly.react(div, data, layout, PLOT_CONFIG).then(() => {
      probe.renders[id] = (probe.renders[id] || 0) + 1;
    });
  }

  function driftPlot() {
    const rows = sortedFrames().filter((r) => r.t_s !== null);
    const data = [];
    const axes = [["x", "x_nm", "pred_x_nm", 1, "y"], ["y", "y_nm", "pred_y_nm", 2, "y2"]];
    for (const [name, key, pkey, col, yaxis] of axes) {
      const band = rows.filter((r) => r[pkey] !== null && r.pred_sigma_nm !== null);
      if (band.length > 0) {
        data.push({
          x: band.map((r) => r.t_s).concat(band.map((r) => r.t_s).reverse()),
          y: band.map((r) => r[pkey] + r.pred_sigma_nm)
            .concat(band.map((r) => r[pkey] - r.pred_sigma_nm).reverse()),
          mode: "lines", fill: "toself", fillcolor: COLORS.band, line: { width: 0 }, hoverinfo: "skip",
          name: "prediction ± σ", legendgroup: "band", showlegend: col === 1, yaxis: yaxis, type: "scatter",
        });
      }
      const meas = rows.filter((r) => r[key] !== null);
      data.push({
        x: meas.map((r) => r.t_s), y: meas.map((r) => r[key]),
        error_y: { type: "data", array: meas.map((r) => r.sigma_nm || 0), visible: true, thickness: 1, width: 0 },
        mode: "markers", marker: { size: 5, color: COLORS[name] },
        name: "measured p", legendgroup: "meas", showlegend: col === 1, yaxis: yaxis, type: "scatter",
        text: meas.map((r) => "frame " + r.seq + (r.reason ? " (" + r.reason + ")" : "")),
      });
      const pred = rows.filter((r) => r[pkey] !== null);
      data.push({
        x: pred.map((r) => r.t_s), y: pred.map((r) => r[pkey]),
        mode: "markers", marker: { size: 7, symbol: "circle-open", color: COLORS.pred },
        name: "predicted before the frame", legendgroup: "pred", showlegend: col === 1, yaxis: yaxis, type: "scatter",
      });
      if (state.truth.length > 0) {
        data.push({
          x: state.truth.map((p) => p[0]), y: state.truth.map((p) => p[col]),
          mode: "lines", line: { color: COLORS.truth, width: 1.5 },
          name: "true drift", legendgroup: "truth", showlegend: col === 1, yaxis: yaxis, type: "scatter",
        });
      }
    }
    const layout = {
      margin: { l: 60, r: 10, t: 10, b: 40 }, legend: { orientation: "h", y: 1.08 },
      xaxis: T_AXIS, grid: { rows: 2, columns: 1, pattern: "coupled" },
      yaxis: { title: { text: "x (nm)" } }, yaxis2: { title: { text: "y (nm)" } },
      uirevision: "drift",
    };
    const seqs = rows.map((r) => r.seq);
    return render("plot-drift", data, layout).then(() => seqs);
  }

  // Bins holding samples only (an empty bin is a gap in the data, not a value).
  function filled(env) {
    const keep = [];
    env.count.forEach((c, i) => { if (c > 0) keep.push(i); });
    const pick = (arr) => keep.map((i) => arr[i]);
    return {
      t_s: pick(env.t_s), count: pick(env.count), width_s: env.width_s,
      min: env.min.map(pick), max: env.max.map(pick), last: env.last.map(pick), flags: env.flags.map(pick),
    };
  }

  function envelopeTraces(full, j, color, name, yaxis, showlegend) {
    const env = filled(full);
    const t = env.t_s;
    return [
      { x: t, y: env.max[j], mode: "lines", line: { width: 0 }, hoverinfo: "skip", showlegend: false, yaxis: yaxis, type: "scatter" },
      { x: t, y: env.min[j], mode: "lines", line: { width: 0 }, fill: "tonexty", fillcolor: color.replace("rgb", "rgba").replace(")", ",0.25)"),
        hoverinfo: "skip", name: name + " range", showlegend: false, yaxis: yaxis, type: "scatter" },
      { x: t, y: env.last[j], mode: "lines", line: { color: color, width: 1.2 }, name: name, showlegend: showlegend, yaxis: yaxis, type: "scatter" },
    ];
  }

  function offsetPlot() {
    const env = state.offset;
    if (!env || env.t_s.length === 0) {
      $("offset-note").textContent = "no offset samples received";
      return render("plot-offset", [], { margin: { l: 60, r: 10, t: 10, b: 40 }, xaxis: T_AXIS,
        annotations: [{ text: state.summary && state.summary.link.endpoint ? "waiting for offsets" : "a finished run: the offset stream is not recorded", showarrow: false, xref: "paper", yref: "paper", x: 0.5, y: 0.5 }] });
    }
    const data = envelopeTraces(env, 0, "rgb(31,119,180)", "d_x", "y", true)
      .concat(envelopeTraces(env, 1, "rgb(214,39,40)", "d_y", "y2", true));
    const shown = filled(env);
    const marks = [[0, "invalid", "rgba(90,90,90,0.9)"], [1, "clamped", "rgba(255,127,14,0.95)"]];
    for (const [f, name, color] of marks) {
      for (const [j, yaxis] of [[0, "y"], [1, "y2"]]) {
        const y = shown.last[j].map((v, i) => (shown.flags[f][i] > 0 ? v : null));
        data.push({ x: shown.t_s, y: y, mode: "lines+markers", connectgaps: false,
          line: { color: color, width: 5 }, marker: { size: 4, color: color },
          name: name, legendgroup: name, showlegend: j === 0, yaxis: yaxis, type: "scatter" });
      }
    }
    const total = env.count.reduce((a, b) => a + b, 0);
    const source = state.summary && state.summary.offset_source ? "; " + state.summary.offset_source : "";
    $("offset-note").textContent = total + " samples in " + shown.t_s.length + " bins of " + fmt(env.width_s, 3) + " s (range and last value per bin)" + source;
    return render("plot-offset", data, {
      margin: { l: 60, r: 10, t: 10, b: 40 }, legend: { orientation: "h", y: 1.15 }, xaxis: T_AXIS,
      grid: { rows: 2, columns: 1, pattern: "coupled" },
      yaxis: { title: { text: "d_x (nm)" } }, yaxis2: { title: { text: "d_y (nm)" } }, uirevision: "offset",
    });
  }

  // Where a model change took effect: between its last frame and the next one.
  function changeTimes() {
    const s = state.summary;
    const changes = (s && s.model_changes) || [];
    const out = [];
    for (const c of changes) {
      const before = state.frames.get(c.seq);
      const after = state.frames.get(c.seq + 1);
      let t = null;
      if (before && after && before.t_s !== null && after.t_s !== null) t = (before.t_s + after.t_s) / 2;
      else if (before && before.t_end_s !== null && before.t_end_s !== undefined) t = before.t_end_s;
      else if (c.t_s !== null) t = c.t_s;
      if (t !== null) out.push({ t: t, label: c.command + (c.term ? " " + c.term : "") });
    }
    return out;
  }

  function errorPlot() {
    const rows = sortedFrames().filter((r) => r.t_s !== null);
    const err = rows.filter((r) => r.pred_error_nm !== null);
    const roll = rows.filter((r) => r.roll_error_nm !== null && r.roll_error_nm !== undefined);
    const data = [
      { x: err.map((r) => r.t_s), y: err.map((r) => r.pred_error_nm), mode: "markers",
        marker: { size: 5, color: "#9467bd" }, name: "|p − prediction|", type: "scatter" },
      { x: roll.map((r) => r.t_s), y: roll.map((r) => r.roll_error_nm), mode: "lines",
        line: { color: "#1d2330", width: 2 }, name: "rolling mean", type: "scatter" },
    ];
    const s = state.summary;
    const tr = s && s.trend;
    const window = s ? s.rolling_window : null;
    if (tr) {
      $("trend-note").textContent = "rolling mean over " + window + " frames; trend over the last " + tr.frames + " frames: " + fmt(tr.nm_per_h, 2) + " nm/h (" + tr.word + ")";
    } else {
      $("trend-note").textContent = err.length ? "too few errors for a trend" : "no prediction errors yet";
    }
    const marks = changeTimes();
    probe.changeMarks = marks.length;
    return render("plot-error", data, {
      margin: { l: 60, r: 10, t: 10, b: 40 }, legend: { orientation: "h", y: 1.12 },
      xaxis: T_AXIS, yaxis: { title: { text: "error (nm)" }, rangemode: "tozero" }, uirevision: "error",
      shapes: marks.map((m) => ({ type: "line", xref: "x", yref: "paper", x0: m.t, x1: m.t, y0: 0, y1: 1, line: { color: "#1f7a3d", width: 2, dash: "dash" } })),
      annotations: marks.map((m) => ({ x: m.t, xref: "x", y: 1, yref: "paper", yanchor: "bottom", text: "model: " + m.label, showarrow: false, font: { size: 10, color: "#1f7a3d" } })),
    });
  }

  // The evidence of the live finding: the one-step errors beside the channel the
  // candidate responds to, over the frames diagnosed and since.
  function evidencePlot() {
    const s = state.summary;
    const live = s && s.live_diagnosis;
    if (!live) return render("plot-evidence", [], { margin: { l: 60, r: 10, t: 10, b: 40 }, xaxis: T_AXIS, uirevision: "evidence" });
    const rows = sortedFrames().filter((r) => r.seq >= live.first_frame && r.t_s !== null && r.pred_x_nm !== null && r.x_nm !== null);
    const data = [
      { x: rows.map((r) => r.t_s), y: rows.map((r) => r.x_nm - r.pred_x_nm), mode: "markers", marker: { size: 5, color: COLORS.x }, name: "error x (nm)", type: "scatter" },
      { x: rows.map((r) => r.t_s), y: rows.map((r) => r.y_nm - r.pred_y_nm), mode: "markers", marker: { size: 5, color: COLORS.y }, name: "error y (nm)", type: "scatter" },
    ];
    const layout = { margin: { l: 60, r: 60, t: 10, b: 40 }, legend: { orientation: "h", y: 1.15 }, xaxis: T_AXIS,
      yaxis: { title: { text: "one-step error (nm)" } }, uirevision: "evidence", shapes: [] };
    const cand = live.candidate;
    if (cand && cand.channel && state.channels[cand.channel]) {
      for (const tr of envelopeTraces(state.channels[cand.channel], 0, "rgb(44,160,44)", cand.channel, "y2", true)) data.push(tr);
      layout.yaxis2 = { title: { text: cand.channel }, overlaying: "y", side: "right" };
    }
    if (rows.length) {
      const last = state.frames.get(live.last_frame);
      if (last && last.t_s !== null) layout.shapes.push({ type: "line", xref: "x", yref: "paper", x0: last.t_s, x1: last.t_s, y0: 0, y1: 1, line: { color: "#5a6275", width: 1, dash: "dot" } });
    }
    return render("plot-evidence", data, layout);
  }

  function csrf() {
    const m = document.querySelector('meta[name="afmdrift-csrf"]');
    return m ? m.content : "";
  }

  function addTerm() {
    const s = state.summary;
    const cand = s && s.live_diagnosis && s.live_diagnosis.candidate;
    if (!cand) return;
    const button = $("add-term");
    button.disabled = true;
    $("add-term-status").textContent = "asking the daemon to add " + cand.term + "…";
    fetch("control/add_term", {
      method: "POST", credentials: "same-origin",
      headers: { "Content-Type": "application/json", "X-Afmdrift-Csrf": csrf() },
      body: JSON.stringify({ term: cand.term }),
    }).then((r) => r.json().then((body) => {
      probe.addTerm = { status: r.status, body: body };
      $("add-term-status").textContent = body.ok ? "added: the model now has " + (body.terms || []).join(", ") : "refused: " + body.error;
      if (!body.ok) button.disabled = false;
    })).catch((e) => {
      probe.addTerm = { status: 0, body: { ok: false, error: String(e) } };
      $("add-term-status").textContent = "no answer from the dashboard: " + e;
      button.disabled = false;
    });
  }

  function liveText() {
    const s = state.summary;
    const live = s.live_diagnosis;
    const control = s.control || { enabled: false, reason: "" };
    if (live) {
      $("live-finding").textContent = live.plain_finding || live.finding;
      $("live-note").textContent = "diagnosis " + live.look + " of this run, frames " + live.first_frame + "–" + live.last_frame +
        " (" + fmt(live.duration_s, 1) + " s), candidates tested at α = " + (live.alpha === null ? "–" : Number(live.alpha).toPrecision(2)) +
        (live.run_alpha ? " so that the whole run stays at " + live.run_alpha : "");
    }
    const cand = live && live.candidate;
    const terms = (s.status && s.status.terms) || (live && live.model_effects) || [];
    const have = cand && terms.indexOf(cand.term) >= 0;
    $("live-candidate").hidden = !cand;
    if (cand) {
      $("add-term-term").textContent = cand.term;
      const button = $("add-term");
      const pending = probe.addTerm === null ? false : probe.addTerm.body && probe.addTerm.body.ok && probe.addTerm.body.term === cand.term;
      button.disabled = !control.enabled || have || pending;
      button.title = !control.enabled ? control.reason : have ? cand.term + " is in the model" : "send add_term " + cand.term + " to the daemon";
      if (!control.enabled) $("add-term-status").textContent = control.reason;
      else if (have && !pending) $("add-term-status").textContent = cand.term + " is in the model already";
    }
    const changes = s.model_changes || [];
    const last = changes.length ? changes[changes.length - 1] : null;
    if (last) {
      const what = last.command + (last.term ? " " + last.term : "") + " after frame " + last.seq;
      const e = last.effect;
      $("change-text").textContent = e
        ? "Since " + what + ": one-step error RMS " + fmt(e.after_rms_nm) + " nm over the " + e.frames + " frames after, against " +
          fmt(e.before_rms_nm) + " nm over the " + e.frames + " frames before" + (e.ratio === null ? "" : " (× " + fmt(e.ratio, 2) + ")") + "."
        : what + ": waiting for frames predicted by the new model.";
    } else {
      $("change-text").textContent = "";
    }
  }

  function framePlot() {
    const rows = sortedFrames();
    const latest = rows.length ? rows[rows.length - 1] : null;
    const v = state.view;
    const lines = [];
    if (latest) {
      lines.push("Frame " + latest.seq + " at t = " + fmt(latest.t_s, 1) + " s: drift p = (" + fmt(latest.x_nm) + ", " + fmt(latest.y_nm) + ") nm, σ = " + fmt(latest.sigma_nm, 3) + " nm, increment (" + fmt(latest.dx_nm) + ", " + fmt(latest.dy_nm) + ") nm, " + latest.valid_blocks + "/" + latest.total_blocks + " blocks" + (latest.reason ? "; " + latest.reason : "") + ".");
      const f = latest.field;
      if (f) {
        lines.push("Block field (published summary, valid blocks): mean (" + fmt(f.mean_dx_nm) + ", " + fmt(f.mean_dy_nm) + ") nm, spread (" + fmt(f.std_dx_nm) + ", " + fmt(f.std_dy_nm) + ") nm, median peak " + fmt(f.median_confidence, 3) + ".");
      }
    }
    const data = [];
    const layout = { margin: { l: 45, r: 10, t: 10, b: 40 }, legend: { orientation: "h", y: 1.1 },
      xaxis: { title: { text: "x (px)" }, constrain: "domain" }, yaxis: { title: { text: "y (px)" }, scaleanchor: "x" }, uirevision: "frame" };
    if (v && v.z) {
      const s = v.scale;
      data.push({ z: v.z, x0: s / 2, dx: s, y0: s / 2, dy: s, type: "heatmap", colorscale: "Greys",
        zmin: v.clim[0], zmax: v.clim[1], showscale: false, name: "x-gradient", hoverinfo: "skip" });
      const seg = (mask) => {
        const xs = [], ys = [];
        v.centres_px.forEach((c, i) => {
          if (!mask[i] || v.vectors_px[i][0] === null) return;
          xs.push(c[0], c[0] + v.gain * v.vectors_px[i][0], null);
          ys.push(c[1], c[1] + v.gain * v.vectors_px[i][1], null);
        });
        return [xs, ys];
      };
      const valid = v.valid;
      const rejected = v.measured.map((m, i) => m && !valid[i]);
      const [vx, vy] = seg(valid);
      const [rx, ry] = seg(rejected);
      data.push({ x: vx, y: vy, mode: "lines", line: { color: "#2ca02c", width: 2 }, name: "valid (" + valid.filter(Boolean).length + ")", type: "scatter" });
      data.push({ x: rx, y: ry, mode: "lines", line: { color: "#d62728", width: 2 }, name: "rejected", type: "scatter" });
      const rc = v.centres_px.filter((c, i) => rejected[i]);
      data.push({ x: rc.map((c) => c[0]), y: rc.map((c) => c[1]), mode: "markers", marker: { symbol: "x", size: 9, color: "#d62728" }, name: "rejected (" + rc.length + ")", type: "scatter" });
      const nm = v.centres_px.filter((c, i) => !v.measured[i]);
      data.push({ x: nm.map((c) => c[0]), y: nm.map((c) => c[1]), mode: "markers", marker: { symbol: "circle-open", size: 10, color: "#ff7f0e" }, name: "no peak (" + nm.length + ")", type: "scatter" });
      layout.xaxis.range = [0, v.shape[1]];
      layout.yaxis.range = [0, v.shape[0]];
      const r = v.result;
      $("frame-note").textContent = "frame " + v.seq + ", re-measured against frame " + v.reference_seq;
      lines.push("Image: x-gradient of frame " + v.seq + "; arrows ×" + fmt(v.gain, 1) + " are block motions re-measured by the dashboard against frame " + v.reference_seq + " (the daemon's own block vectors are not published): " + (r.valid ? "(" + fmt(r.dx_nm) + ", " + fmt(r.dy_nm) + ") nm, σ = " + fmt(r.sigma_nm, 3) + " nm, " + r.valid_blocks + "/" + r.total_blocks + " blocks." : "invalid (" + r.reason + ")."));
    } else {
      $("frame-note").textContent = latest ? "frame " + latest.seq + ": no image" : "no frame yet";
      const why = v && (v.note || v.error) ? (v.note || v.error) : "waiting for a frame";
      lines.push("No image: " + why + ".");
      // Still draw the published field summary, so the plot is never blank when a frame exists.
      const f = latest && latest.field;
      if (f && f.mean_dx_nm !== null) {
        data.push({ x: [0, f.mean_dx_nm], y: [0, f.mean_dy_nm], mode: "lines+markers", line: { color: "#2ca02c", width: 3 }, name: "mean block motion (nm)", type: "scatter" });
        data.push({ x: [f.mean_dx_nm], y: [f.mean_dy_nm], error_x: { type: "data", array: [f.std_dx_nm || 0] }, error_y: { type: "data", array: [f.std_dy_nm || 0] }, mode: "markers", marker: { color: "#2ca02c" }, name: "spread of the blocks", type: "scatter" });
        layout.xaxis.title.text = "dx (nm)";
        layout.yaxis.title.text = "dy (nm)";
      }
    }
    $("frame-text").textContent = lines.join(" ");
    return render("plot-frame", data, layout);
  }

  function channelsPlot() {
    const names = Object.keys(state.channels).sort();
    const data = [];
    const layout = { margin: { l: 60, r: 10, t: 10, b: 40 }, legend: { orientation: "h", y: 1.12 }, xaxis: T_AXIS, uirevision: "channels", shapes: [] };
    const rows = names.length + 1;
    layout.grid = { rows: rows, columns: 1, pattern: "coupled", roworder: "top to bottom" };
    const palette = ["rgb(140,86,75)", "rgb(23,190,207)", "rgb(188,189,34)", "rgb(127,127,127)", "rgb(227,119,194)"];
    names.forEach((name, i) => {
      const yaxis = i === 0 ? "y" : "y" + (i + 1);
      const key = i === 0 ? "yaxis" : "yaxis" + (i + 1);
      layout[key] = { title: { text: name, font: { size: 10 } } };
      for (const tr of envelopeTraces(state.channels[name], 0, palette[i % palette.length], name, yaxis, true)) data.push(tr);
    });
    const evAxis = rows === 1 ? "y" : "y" + rows;
    layout[rows === 1 ? "yaxis" : "yaxis" + rows] = { title: { text: "events", font: { size: 10 } }, type: "category" };
    const evs = state.events.slice(-MAX_EVENTS_DRAWN);
    data.push({ x: evs.map((e) => e.t_s), y: evs.map((e) => e.kind), mode: "markers", marker: { symbol: "triangle-down", size: 10, color: "#1d2330" },
      text: evs.map((e) => e.kind + " (" + fmt(e.x_nm, 1) + ", " + fmt(e.y_nm, 1) + ") nm"), name: "events", yaxis: evAxis, type: "scatter" });
    for (const e of evs) {
      layout.shapes.push({ type: "line", xref: "x", yref: "paper", x0: e.t_s, x1: e.t_s, y0: 0, y1: 1, line: { color: "rgba(29,35,48,0.25)", width: 1, dash: "dot" } });
    }
    const s = state.summary;
    let note = names.length ? "" : "No channels logged. ";
    if (!evs.length) note += "No events logged.";
    if (s && !s.store_note) note += " Channels and events come from the run store; no run directory is followed.";
    else if (s && s.store_state === "waiting") note += " Channels and events come from the run store, which does not exist yet.";
    $("channels-note").textContent = note.trim();
    $("plot-channels").style.height = Math.max(220, 110 * rows) + "px";
    return render("plot-channels", data, layout);
  }

  // ------------------------------------------------------------------ text

  function badge(el, text, cls) { el.textContent = text; el.className = "badge " + (cls || ""); }

  function summaryText() {
    const s = state.summary;
    if (!s) return;
    badge($("daemon-link"), s.link.state, s.link.endpoint === null ? "" : s.link.live ? "ok" : "bad");
    // The run store, when it is not simply open: awaited (live, before the
    // daemon has created it) or unreadable. The facts line gives the whole note.
    const store = $("store-link");
    store.hidden = s.store_state !== "waiting" && s.store_state !== "error";
    if (!store.hidden) {
      badge(store, s.store_state === "waiting" ? "waiting for " + s.store_path : "run store unreadable", s.store_state === "waiting" ? "warn" : "bad");
      store.title = s.store_note;
    }
    const st = s.status;
    const flags = $("flags");
    flags.textContent = "";
    if (st && s.link.endpoint !== null) {
      badge($("service-state"), "service " + st.state + ", " + st.frames + " frames", st.state === "running" ? "ok" : "warn");
      for (const f of st.flags) {
        const b = document.createElement("span");
        badge(b, f, f === "instrument_error" || f === "stale" || f === "store_error" || f === "frame_error" ? "bad" : "warn");
        if (f === "store_error" && st.store_problem) b.title = st.store_problem + " (" + st.frames_held + " frames held)";
        if (f === "frame_error" && st.frame_problem) b.title = st.frame_problem;
        flags.appendChild(b);
      }
    } else {
      badge($("service-state"), s.link.endpoint === null ? "finished run, " + s.frames_kept + " frames" : "no status yet", "");
    }
    $("predictor").textContent = s.predictor || (s.model && s.model.predictor) || "–";
    const m = s.model || {};
    const eff = [];
    if (m.terms) eff.push("configured: " + m.terms.join(", "));
    if (m.active) eff.push("active: " + m.active.join(", "));
    $("effects").textContent = eff.length ? eff.join("; ") : (s.predictor ? "the predictor has no effect terms" : "–");
    const latest = s.latest_frame;
    const roll = st && st.rolling_error_nm !== null ? st.rolling_error_nm : latest ? latest.roll_error_nm : null;
    $("error-text").textContent = roll === null || roll === undefined ? "–" : "rolling mean " + fmt(roll) + " nm" + (s.trend ? ", " + s.trend.word : "");
    $("truth-text").textContent = s.truth ? s.truth + (s.truth_aligned ? ", shifted to 0 over the reference frame" : " (waiting for the reference frame)") : "not available (give --session with a truth.csv for a simulated or recorded session)";
    $("store-text").textContent = s.store_note || "none (only what the daemon publishes)";
    const d = s.diagnosis;
    if (d) {
      $("diagnosis-finding").textContent = d.finding;
      $("diagnosis-config").textContent = d.config || "(no configuration line to add)";
    } else {
      $("diagnosis-finding").textContent = "No diagnose result for this run. Run `afmdrift diagnose RUN_DIR --json > RUN_DIR/diagnosis.json` to show its finding here.";
      $("diagnosis-config").textContent = "";
    }
    $("diagnosis-note").textContent = s.diagnosis_note || "";
    liveText();
  }

  // ------------------------------------------------------------------ scheduling

  let busy = Promise.resolve();
  function queue(fn) { busy = busy.then(fn).catch((e) => { probe.lastError = String(e); console.error(e); }); return busy; }

  function renderAll() {
    return queue(() => Promise.all([driftPlot(), offsetPlot(), errorPlot(), framePlot(), channelsPlot(), evidencePlot()]));
  }

  function onFrames(msg) {
    const fresh = upsertFrames(msg.rows);
    if (msg.truth_reset) state.truth = msg.truth; else state.truth = state.truth.concat(msg.truth);
    // Thinned by half above the server's cap, as the server does.
    if (state.truth.length > MAX_TRUTH_POINTS) state.truth = state.truth.filter((p, i) => i % 2 === 0);
    const received = Date.now();
    return queue(() => driftPlot().then(() => {
      const now = Date.now();
      for (const row of fresh) {
        probe.frameShown[row.seq] = now;
        if (row.wall_s !== null) probe.latenciesMs.push(now - 1000 * row.wall_s);
        if (probe.latenciesMs.length > MAX_LATENCIES) probe.latenciesMs.splice(0, probe.latenciesMs.length - MAX_LATENCIES);
      }
      probe.lastFrameReceivedMs = received;
      return Promise.all([errorPlot(), framePlot(), evidencePlot()]);
    }));
  }

  function onMessage(ev) {
    const msg = JSON.parse(ev.data);
    probe.messages += 1;
    if (msg.type === "snapshot") {
      probe.snapshots += 1;
      state.frames = new Map();
      upsertFrames(msg.frames);
      state.truth = msg.truth;
      state.offset = msg.offset;
      state.channels = msg.channels;
      state.events = msg.events;
      state.view = msg.frame_view;
      state.summary = msg.summary;
      summaryText();
      renderAll();
    } else if (msg.type === "frames") {
      onFrames(msg);
    } else if (msg.type === "tick") {
      state.offset = mergeEnvelope(state.offset, msg.offset);
      for (const name of Object.keys(msg.channels)) {
        state.channels[name] = mergeEnvelope(state.channels[name], msg.channels[name]);
      }
      state.events = state.events.concat(msg.events).slice(-2000);
      state.summary = msg.summary;
      summaryText();
      queue(() => Promise.all([offsetPlot(), msg.events.length ? channelsPlot() : null,
        Object.keys(msg.channels).length ? channelsPlot() : null, errorPlot(), evidencePlot()]));
    } else if (msg.type === "frame_view") {
      state.view = msg.view;
      queue(framePlot);
    }
  }

  let delayMs = 250;
  function connect() {
    const scheme = location.protocol === "https:" ? "wss://" : "ws://";
    const ws = new WebSocket(scheme + location.host + "/ws");
    ws.onopen = () => {
      probe.connected = true;
      probe.connects += 1;
      delayMs = 250;
      badge($("page-link"), "dashboard connected", "ok");
    };
    ws.onmessage = onMessage;
    ws.onclose = () => {
      probe.connected = false;
      badge($("page-link"), "dashboard connection lost, reconnecting…", "bad");
      setTimeout(connect, delayMs);
      delayMs = Math.min(5000, delayMs * 2);
    };
  }
  $("add-term").addEventListener("click", addTerm);
  connect();
})();

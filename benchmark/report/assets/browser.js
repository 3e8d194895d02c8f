// The frame browser of report.html (benchmark/report/html.py writes the page, browser.py the data):
// a sortable, filterable table of the frames and, for the chosen one, the ground truth and each run's
// prediction as SVG in the BEV frame (x right, y forward), edges coloured by the metric's matching.
"use strict";
(function () {
  const root = document.getElementById("frame-browser");
  const messages = root.querySelector(".messages");
  const PAGE = 200; // table rows drawn at a time
  const SVG = "http://www.w3.org/2000/svg";

  function say(text, kind) {
    const p = document.createElement("p");
    p.className = kind || "problem";
    p.textContent = text;
    messages.appendChild(p);
    return p;
  }

  function element(name, attributes, text) {
    const e = document.createElement(name);
    for (const key in attributes || {}) e.setAttribute(key, attributes[key]);
    if (text !== undefined) e.textContent = text;
    return e;
  }

  function svgElement(name, attributes) {
    const e = document.createElementNS(SVG, name);
    for (const key in attributes) e.setAttribute(key, attributes[key]);
    return e;
  }

  const state = (word) => document.body.setAttribute("data-browser", word);
  // whatever fails below (data of another format, a bug) says so in the page rather than leave it blank
  window.addEventListener("error", (event) => {
    say("The frame browser stopped: " + event.message + ". The tables above are complete.");
    state("stopped");
  });

  let data;
  try {
    data = JSON.parse(document.getElementById("browser-data").textContent);
  } catch (error) {
    say("The frame browser's data could not be read (" + error.message + "); the tables above are complete.");
    state("stopped");
    return;
  }
  for (const note of data.notes) say(note, "note");
  const F = data.frames;
  const N = F.id.length;
  if (!N) {
    say(data.empty || "No frame to browse.");
    state("ready");
    return;
  }
  if (data.left_out) {
    say(N + " of the " + data.total + " evaluated frames are here (--browser-frames " + data.limit + "): " +
        data.left_out + " left out. Each kept frame says why it is here.", "note");
  }
  const S = data.style;
  const runs = data.runs;
  const percent = (v) => (v === null || v === undefined ? null : 100 * v);
  const shown = (v, digits) => (v === null || v === undefined ? "–" : v.toFixed(digits === undefined ? 1 : digits));
  const unique = new Map(); // frame id -> how many blocks hold it (a Map: an id may be "constructor")
  for (const id of F.id) unique.set(id, (unique.get(id) || 0) + 1);

  // ---- columns: what the table shows and sorts by
  const columns = [
    {label: "frame", text: true, value: (i) => F.id[i]},
    {label: "data", text: true, value: (i) => data.blocks[F.block[i]].label},
    {label: "kept because", text: true, value: (i) => F.why[i].map((r) => data.reasons[r]).join("; ")},
    {label: "junctions", value: (i) => F.junctions[i], digits: 0},
    {label: "lane length (m)", value: (i) => F.length[i], digits: 1},
  ];
  runs.forEach((run, r) => {
    columns.push({label: run.name + " dir TOPO F1", value: (i) => percent(data.scores[r].f1[i]), run: r});
    // "none": the run scored the frame and it has no junction; "–": the run did not score the frame
    columns.push({label: run.name + " dir J-TOPO F1", value: (i) => percent(data.scores[r].jf1[i]), run: r,
                  none: (i) => (data.scores[r].scored[i] && F.junctions[i] === 0 ? "none" : "–")});
  });

  // ---- controls
  const controls = root.querySelector(".controls");
  function select(options, name) {
    const s = element("select", {name: name});
    options.forEach(([value, text]) => s.appendChild(element("option", {value: value}, text)));
    return s;
  }
  function number(name, value) {
    return element("input", {type: "number", name: name, value: value === undefined ? "" : value, step: "any"});
  }
  function group(title, ...parts) {
    const f = element("fieldset");
    f.appendChild(element("legend", {}, title));
    parts.forEach((p) => f.appendChild(typeof p === "string" ? document.createTextNode(p) : p));
    controls.appendChild(f);
  }
  const runOptions = runs.map((run, r) => [String(r), run.name]);
  const metricOptions = [["f1", "dir TOPO F1"], ["jf1", "dir J-TOPO F1"]];
  const blockFilter = select([["", "all"]].concat(data.blocks.map((b, k) => [String(k), b.label])), "data");
  const minJunctions = number("junctions-min"), maxJunctions = number("junctions-max");
  const belowRun = select([["", "–"]].concat(runOptions), "below-run");
  const belowMetric = select(metricOptions, "below-metric");
  const belowValue = number("below-value");
  const diffA = select([["", "–"]].concat(runOptions), "diff-a");
  const diffB = select([["", "–"]].concat(runOptions), "diff-b");
  const diffMetric = select(metricOptions, "diff-metric");
  const diffValue = number("diff-value");
  group("dataset and split", blockFilter);
  group("junctions", "from ", minJunctions, " to ", maxJunctions);
  group("F1 below (%)", belowRun, " ", belowMetric, " < ", belowValue);
  group("difference above (%)", diffA, " − ", diffB, " ", diffMetric, " > ", diffValue);
  const reset = element("button", {type: "button", name: "reset"}, "reset");
  controls.appendChild(reset);
  const count = element("span", {class: "count"});
  controls.appendChild(count);

  // ---- state
  let order = [];        // the filtered frames, sorted
  let sortColumn = null, sortDown = false, page = 0, current = -1;

  const value = (input) => (input.value === "" ? null : Number(input.value));

  function passes(i) {
    if (blockFilter.value !== "" && F.block[i] !== Number(blockFilter.value)) return false;
    const low = value(minJunctions), high = value(maxJunctions);
    if (low !== null && F.junctions[i] < low) return false;
    if (high !== null && F.junctions[i] > high) return false;
    const below = value(belowValue);
    if (belowRun.value !== "" && below !== null) {
      const v = percent(data.scores[Number(belowRun.value)][belowMetric.value][i]);
      if (v === null || !(v < below)) return false;
    }
    const gap = value(diffValue);
    if (diffA.value !== "" && diffB.value !== "" && gap !== null) {
      const a = percent(data.scores[Number(diffA.value)][diffMetric.value][i]);
      const b = percent(data.scores[Number(diffB.value)][diffMetric.value][i]);
      if (a === null || b === null || !(a - b > gap)) return false;
    }
    return true;
  }

  function refresh() {
    order = [];
    for (let i = 0; i < N; i++) if (passes(i)) order.push(i);
    if (sortColumn !== null) {
      const c = columns[sortColumn], sign = sortDown ? -1 : 1;
      const keys = order.map((i) => c.value(i));
      const at = new Map(order.map((i, k) => [i, k]));
      order.sort((a, b) => {
        const x = keys[at.get(a)], y = keys[at.get(b)];
        if (x === null || y === null) return x === null ? (y === null ? a - b : 1) : -1; // none last
        if (x < y) return -sign;
        if (x > y) return sign;
        return a - b;
      });
    }
    page = 0;
    count.textContent = order.length + " of " + N + " frames";
    drawTable();
  }

  // ---- the table
  const area = root.querySelector(".table-area");
  const table = element("table", {class: "frames"});
  const head = element("thead"), body = element("tbody");
  const headRow = element("tr");
  columns.forEach((c, k) => {
    const th = element("th", {"data-column": String(k)}, c.label);
    th.addEventListener("click", () => {
      sortDown = sortColumn === k ? !sortDown : false;
      sortColumn = k;
      refresh();
    });
    headRow.appendChild(th);
  });
  head.appendChild(headRow);
  table.appendChild(head);
  table.appendChild(body);
  area.appendChild(table);
  const pager = element("div", {class: "pager"});
  area.after(pager);

  function drawTable() {
    headRow.querySelectorAll("th").forEach((th, k) => {
      th.className = k === sortColumn ? (sortDown ? "sorted-down" : "sorted-up") : "";
    });
    const rows = document.createDocumentFragment();
    const first = page * PAGE;
    for (const i of order.slice(first, first + PAGE)) {
      const tr = element("tr", {"data-frame": F.id[i], "data-index": String(i)});
      if (i === current) tr.className = "chosen";
      for (const c of columns) {
        const v = c.value(i);
        const text = c.text ? v : v === null && c.none ? c.none(i) : shown(v, c.digits);
        tr.appendChild(element("td", c.text ? {title: v} : {class: "num"}, text));
      }
      tr.addEventListener("click", () => choose(i, true));
      rows.appendChild(tr);
    }
    body.replaceChildren(rows);
    pager.replaceChildren();
    if (order.length > PAGE) {
      const pages = Math.ceil(order.length / PAGE);
      const previous = element("button", {type: "button"}, "◀ previous");
      const next = element("button", {type: "button"}, "next ▶");
      previous.disabled = page === 0;
      next.disabled = page >= pages - 1;
      previous.addEventListener("click", () => { page--; drawTable(); });
      next.addEventListener("click", () => { page++; drawTable(); });
      pager.append(previous, " rows " + (first + 1) + "–" + Math.min(first + PAGE, order.length) + " of " +
                   order.length + " ", next);
    }
  }

  [blockFilter, minJunctions, maxJunctions, belowRun, belowMetric, belowValue, diffA, diffB, diffMetric,
   diffValue].forEach((input) => input.addEventListener("input", refresh));
  reset.addEventListener("click", () => {
    controls.querySelectorAll("input").forEach((input) => { input.value = ""; });
    controls.querySelectorAll("select").forEach((s) => { s.selectedIndex = 0; });
    refresh();
  });

  // ---- a frame's drawing: varints in base64 (browser.py's frame_drawing)
  function reader(text) {
    const bytes = atob(text);
    let at = 0;
    return function next() {
      let v = 0, scale = 1, b;
      do {
        b = bytes.charCodeAt(at++);
        v += (b & 127) * scale;
        scale *= 128;
      } while (b & 128);
      return v;
    };
  }
  const signed = (v) => (v % 2 ? -(v + 1) / 2 : v / 2);

  function graphOf(next) {
    const nv = next(), ne = next();
    const x = new Float64Array(nv), y = new Float64Array(nv);
    let qx = 0, qy = 0;
    for (let v = 0; v < nv; v++) {
      qx += signed(next()); qy += signed(next());
      x[v] = qx * data.quantum; y[v] = qy * data.quantum;
    }
    const src = new Int32Array(ne), dst = new Int32Array(ne);
    let s = 0;
    for (let e = 0; e < ne; e++) { s += signed(next()); src[e] = s; dst[e] = s + signed(next()); }
    const arrows = [];
    for (let k = next(); k > 0; k--) arrows.push(next());
    return {x, y, src, dst, arrows};
  }

  function decode(i) {
    const next = reader(F.drawing[i]);
    const gt = graphOf(next);
    const predictions = [];
    runs.forEach((run, r) => {
      if (run.block !== F.block[i] || !run.drawn) return; // a run without predictions has no drawing
      const graph = graphOf(next);
      const shares = Array.from({length: graph.src.length}, next);
      const found = Array.from({length: gt.src.length}, next);
      const predicted = next() === 1;
      predictions.push({run: r, graph, shares, found, predicted});
    });
    return {gt, predictions};
  }

  function drawing(graph, shares, range, label) {
    const [x0, x1, y0, y1] = range;
    const width = 220, height = Math.round(width * (y1 - y0) / (x1 - x0));
    const svg = svgElement("svg", {viewBox: x0 + " " + -y1 + " " + (x1 - x0) + " " + (y1 - y0), width, height,
                                   role: "img", "aria-label": label});
    svg.appendChild(svgElement("rect", {x: x0, y: -y1, width: x1 - x0, height: y1 - y0, fill: S.background}));
    const edges = svgElement("g", {"stroke-width": S.svg_edge_width, "stroke-linecap": "round",
                                   class: "edges"});
    const colour = (e) => (shares[e] >= 50 ? S.matched : S.unmatched);
    for (let e = 0; e < graph.src.length; e++) {
      const s = graph.src[e], d = graph.dst[e];
      const line = svgElement("line", {x1: graph.x[s], y1: -graph.y[s], x2: graph.x[d], y2: -graph.y[d],
                                       stroke: colour(e),
                                       class: "edge " + (shares[e] >= 50 ? "matched" : "unmatched")});
      line.appendChild(svgElement("title", {})).textContent = shares[e] + " % of this edge paired";
      edges.appendChild(line);
    }
    svg.appendChild(edges);
    for (const e of graph.arrows) {
      const s = graph.src[e], d = graph.dst[e];
      const dx = graph.x[d] - graph.x[s], dy = graph.y[d] - graph.y[s], length = Math.hypot(dx, dy);
      if (!length) continue;
      const ux = dx / length, uy = dy / length, mx = (graph.x[s] + graph.x[d]) / 2, my = (graph.y[s] + graph.y[d]) / 2;
      const tipX = mx + S.arrow_half_length * ux, tipY = my + S.arrow_half_length * uy;
      const baseX = tipX - S.arrow_head * ux, baseY = tipY - S.arrow_head * uy;
      const side = S.arrow_head * S.arrow_head_side;
      svg.appendChild(svgElement("line", {x1: mx - S.arrow_half_length * ux, y1: -(my - S.arrow_half_length * uy),
                                          x2: baseX, y2: -baseY, stroke: colour(e), "stroke-width": S.svg_arrow_width,
                                          class: "arrow"}));
      const head = [[tipX, tipY], [baseX - side * uy, baseY + side * ux], [baseX + side * uy, baseY - side * ux]];
      svg.appendChild(svgElement("polygon", {points: head.map(([px, py]) => px + "," + -py).join(" "),
                                             fill: colour(e), class: "arrow"}));
    }
    svg.appendChild(svgElement("polygon", {points: S.ego_outline.map(([px, py]) => px + "," + -py).join(" "),
                                           fill: S.ego_fill, stroke: S.ego_edge, "stroke-width": S.svg_ego_edge_width,
                                           class: "ego"}));
    return svg;
  }

  const view = root.querySelector(".frame-view");
  let foundBy = null; // the run whose matching colours the ground truth's edges

  function scoreLine(r, i) {
    const s = data.scores[r];
    const none = s.scored[i] && !F.junctions[i] ? "none (no junction)" : "–";
    const jf1 = s.jf1[i] === null ? none : shown(percent(s.jf1[i]));
    return "dir TOPO P " + shown(percent(s.p[i])) + " R " + shown(percent(s.r[i])) + " F1 " +
           shown(percent(s.f1[i])) + " · dir J-TOPO F1 " + jf1 + " (%)";
  }

  function choose(i, write) {
    current = i;
    body.querySelectorAll("tr.chosen").forEach((tr) => tr.classList.remove("chosen"));
    const row = body.querySelector('tr[data-index="' + i + '"]');
    if (row) { row.classList.add("chosen"); row.scrollIntoView({block: "nearest"}); }
    if (write) {
      let hash = "frame=" + encodeURIComponent(F.id[i]);
      if (unique.get(F.id[i]) > 1) hash += "&data=" + F.block[i];
      history.replaceState(null, "", "#" + hash);
    }
    let frame;
    try {
      frame = decode(i);
    } catch (error) {
      view.replaceChildren(element("p", {class: "problem"}, "Frame " + F.id[i] + " could not be drawn: " + error.message));
      return;
    }
    const block = data.blocks[F.block[i]];
    const title = element("h3", {}, F.id[i]);
    const about = element("p", {class: "note"}, block.label + " · " + F.junctions[i] + " junctions · " +
                          F.length[i].toFixed(1) + " m of lanes · kept because " +
                          F.why[i].map((r) => data.reasons[r]).join("; "));
    const panels = element("div", {class: "panels"});
    if (foundBy === null || !frame.predictions.some((p) => p.run === foundBy)) {
      foundBy = frame.predictions.length ? frame.predictions[0].run : null;
    }
    const gtPanel = element("div", {class: "panel", "data-panel": "ground truth"});
    const found = frame.predictions.find((p) => p.run === foundBy);
    const gtShares = found ? found.found : Array(frame.gt.src.length).fill(0);
    const heading = element("h4", {}, found ? "ground truth, edges found by " : "ground truth");
    if (found) { // the chooser names the drawn runs only: a run without predictions found nothing to show
      const chooser = select(frame.predictions.map((p) => [String(p.run), runs[p.run].name]), "found-by");
      chooser.value = String(foundBy);
      chooser.addEventListener("change", () => { foundBy = Number(chooser.value); choose(i, false); });
      heading.appendChild(chooser);
    }
    gtPanel.appendChild(heading);
    gtPanel.appendChild(drawing(frame.gt, gtShares, block.range, "ground truth"));
    const paired = gtShares.filter((s) => s >= 50).length;
    gtPanel.appendChild(element("div", {class: "scores"}, frame.gt.x.length + " vertices, " + frame.gt.src.length +
                                " edges" + (found ? "; " + paired + " found by " + runs[found.run].name : "")));
    if (F.thumbnail[i]) {
      gtPanel.appendChild(element("img", {class: "thumbnail", src: F.thumbnail[i], alt: "front camera"}));
    }
    panels.appendChild(gtPanel);
    runs.forEach((run, r) => {
      if (run.block !== F.block[i]) return;
      const panel = element("div", {class: "panel", "data-panel": run.name});
      panel.appendChild(element("h4", {}, run.name));
      const p = frame.predictions.find((q) => q.run === r);
      let line = scoreLine(r, i);
      if (!p) {
        panel.appendChild(element("p", {class: "note not-drawn"}, "not drawn: the run has no predictions.parquet"));
      } else {
        panel.appendChild(drawing(p.graph, p.shares, block.range, run.name));
        const empty = data.scores[r].f1[i] === null && !frame.gt.x.length; // nothing to predict
        if (!p.predicted && !empty) line += " · no prediction for this frame";
      }
      panel.appendChild(element("div", {class: "scores"}, line));
      panels.appendChild(panel);
    });
    const legend = element("p", {class: "note"}, "Green: an edge whose densified points the metric's matching " +
                           "paired (half or more), red: not; arrows in the driving direction, one per piece; " +
                           "the ego car in grey. ← → or ↑ ↓ step through the listed frames.");
    view.replaceChildren(title, about, panels, legend);
  }

  function step(by) {
    if (!order.length) return;
    let at = order.indexOf(current);
    at = at < 0 ? 0 : Math.min(order.length - 1, Math.max(0, at + by));
    const wanted = Math.floor(at / PAGE);
    if (wanted !== page) { page = wanted; drawTable(); }
    choose(order[at], true);
  }

  function onScreen() {
    const box = root.getBoundingClientRect();
    return box.top < window.innerHeight && box.bottom > 0;
  }

  // the arrows step only through a chosen frame's list, with the browser in sight: elsewhere they scroll
  document.addEventListener("keydown", (event) => {
    const tag = (event.target.tagName || "").toLowerCase();
    if (tag === "input" || tag === "select" || tag === "textarea") return;
    if (current < 0 || !onScreen()) return;
    if (event.altKey || event.ctrlKey || event.metaKey || event.shiftKey) return;  // the browser's own (Alt+← back)
    if (event.key === "ArrowDown" || event.key === "ArrowRight") { step(1); event.preventDefault(); }
    if (event.key === "ArrowUp" || event.key === "ArrowLeft") { step(-1); event.preventDefault(); }
  });

  let addressProblem = null;
  function fromAddress() {
    if (addressProblem) { addressProblem.remove(); addressProblem = null; }
    const params = new URLSearchParams(location.hash.slice(1));
    const wanted = params.get("frame");
    if (wanted === null) return;
    const dataIndex = params.get("data");
    let i = -1;
    for (let k = 0; k < N; k++) {
      if (F.id[k] === wanted && (dataIndex === null || String(F.block[k]) === dataIndex)) { i = k; break; }
    }
    if (i < 0) {
      addressProblem = say("The address names frame " + wanted + ", which this report does not hold" +
                           (data.left_out ? " (" + data.left_out + " frames were left out: --browser-frames)" : "") +
                           ". Choose a frame in the table.");
      return;
    }
    const at = order.indexOf(i);
    if (at >= 0 && Math.floor(at / PAGE) !== page) { page = Math.floor(at / PAGE); drawTable(); }
    choose(i, false);
    root.scrollIntoView();
  }

  refresh();
  window.addEventListener("hashchange", fromAddress);
  fromAddress();
  performance.mark("browser-ready");
  state("ready");
})();

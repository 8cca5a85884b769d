/* Operator dashboard of the glue cell: plain JavaScript, no framework, no build step.
 *
 * What the server says is the only truth: the state, the commands it allows
 * (available_commands), the messages it answers. The page keeps a copy of the
 * last state it received and shows it as live only while the WebSocket is up.
 */
"use strict";

(() => {
  const TOKEN_KEY = "gluecell.hmi.token";
  const REFRESH_MS = 3000;            // health, KPIs, history
  const RECONNECT_FIRST_MS = 1000;    // then doubled up to RECONNECT_MAX_MS, with jitter
  const RECONNECT_MAX_MS = 10000;
  const WATCHDOG_PING_MS = 10000;     // ask the server for a pong after this much silence
  const WATCHDOG_DEAD_MS = 20000;     // and give the socket up after this much
  const HISTORY_ROWS = 20;

  const STATE_TONE = {
    IDLE: "ok",
    EXECUTING_TRAJECTORY: "busy",
    CALIBRATING_ROBOT: "busy",
    CALIBRATING_CAMERA: "busy",
    CREATING_WORKPIECE: "busy",
    PAUSED: "hold",
    ERROR: "fault",
    INITIALIZING: "init",
  };
  const ENDINGS = {
    OPERATION_COMPLETED: "completed",
    CANCEL_REQUESTED: "cancelled",
    OPERATION_FAILED: "failed",
    EMERGENCY_STOP: "stopped",
    ERROR_OCCURRED: "stopped by a fault",
  };

  const DONE_COLOUR = "#ff4fd8"; // the executed path: unlike anything on the camera frame

  const $ = (id) => document.getElementById(id);

  const hmi = {
    token: null,
    view: null,            // the last StateView received
    enteredAtMs: 0,        // performance.now() when that state was entered
    live: false,
    ws: null,
    lastSeq: null,
    lastMessageMs: 0,
    attempts: 0,
    reconnectTimer: null,
    progress: null,        // {run_id, operation, waypoint, of, fraction, workpiece, ended}
    trajectory: null,
    calibration: null,
    frame: null,           // the latest camera frame an operation captured (an Image)
    frameInfo: null,       // {time, source, run} of that frame (X-Frame-* headers)
    calibrationImage: null, // the annotated frame of the last robot calibration: the fallback
    thumbnails: [],        // blob URLs to release
    pending: new Set(),    // commands whose request is in flight
    counters: { connects: 0, disconnects: 0, messages: 0, gaps: 0 },
    timers: [],
  };

  class AuthError extends Error {}

  // --- HTTP -----------------------------------------------------------------

  async function api(method, path, body) {
    const headers = { Authorization: `Bearer ${hmi.token}` };
    const init = { method, headers, cache: "no-store" };
    if (body !== undefined) {
      headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(body);
    }
    const response = await fetch(path, init);
    if (response.status === 401) {
      const message = await errorText(response);
      signOut(message);
      throw new AuthError(message);
    }
    return response;
  }

  async function getJson(path) {
    const response = await api("GET", path);
    if (!response.ok) throw new Error(`${path}: ${response.status} ${await errorText(response)}`);
    return response.json();
  }

  async function errorText(response) {
    try {
      const body = await response.clone().json();
      return body.message || body.detail || JSON.stringify(body);
    } catch {
      return (await response.text()) || response.statusText;
    }
  }

  async function blobUrl(path) {
    const response = await api("GET", path);
    if (!response.ok) return null;
    return URL.createObjectURL(await response.blob());
  }

  // --- login ----------------------------------------------------------------

  async function tryToken(token) {
    const response = await fetch("/state", {
      headers: { Authorization: `Bearer ${token}` },
      cache: "no-store",
    });
    if (response.ok) return { ok: true, view: await response.json() };
    return { ok: false, message: `${response.status}: ${await errorText(response)}` };
  }

  async function onLogin(event) {
    event.preventDefault();
    const token = $("token-input").value.trim();
    if (!token) return;
    $("login-button").disabled = true;
    try {
      const result = await tryToken(token);
      if (!result.ok) return showLoginError(result.message);
      sessionStorage.setItem(TOKEN_KEY, token);
      $("token-input").value = "";
      startSession(token, result.view);
    } catch (error) {
      showLoginError(`the server cannot be reached: ${error.message}`);
    } finally {
      $("login-button").disabled = false;
    }
  }

  function showLoginError(message) {
    $("login-error").textContent = message;
    $("login-error").hidden = false;
  }

  function showLogin(message) {
    $("app").hidden = true;
    $("login").hidden = false;
    $("login-error").hidden = !message;
    $("login-error").textContent = message || "";
    $("token-input").focus();
  }

  function signOut(message) {
    sessionStorage.removeItem(TOKEN_KEY);
    stopSession();
    showLogin(message);
  }

  function startSession(token, view) {
    hmi.token = token;
    $("login").hidden = true;
    $("app").hidden = false;
    if (view) applyState(view);
    setLive(false, "connecting…");
    connect();
    refreshPanels();
    refreshTrajectory();
    refreshCalibration();
    refreshFrame();
    refreshLibrary();
    hmi.timers.push(setInterval(refreshPanels, REFRESH_MS));
    hmi.timers.push(setInterval(tick, 250));
    hmi.timers.push(setInterval(watchdog, 1000));
  }

  function stopSession() {
    hmi.timers.forEach(clearInterval);
    hmi.timers = [];
    clearTimeout(hmi.reconnectTimer);
    hmi.reconnectTimer = null;
    dropSocket(null);
    hmi.token = null;
  }

  // --- WebSocket ------------------------------------------------------------

  async function connect() {
    clearTimeout(hmi.reconnectTimer);
    hmi.reconnectTimer = null;
    let ticket;
    try {
      const response = await api("POST", "/ws-ticket");
      if (!response.ok) throw new Error(`no ticket (${response.status}: ${await errorText(response)})`);
      ticket = (await response.json()).ticket;
    } catch (error) {
      if (error instanceof AuthError) return;
      const unreachable = error instanceof TypeError; // fetch: no answer at all
      scheduleReconnect(unreachable ? "the server cannot be reached" : error.message);
      return;
    }
    if (!hmi.token) return;
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const ws = new WebSocket(`${scheme}://${location.host}/ws?ticket=${encodeURIComponent(ticket)}`);
    hmi.ws = ws;
    hmi.lastMessageMs = performance.now();
    ws.onmessage = (event) => hmi.ws === ws && onMessage(JSON.parse(event.data));
    ws.onclose = (event) => {
      if (hmi.ws !== ws) return;
      hmi.ws = null;
      scheduleReconnect(closeReason(event));
    };
  }

  function closeReason(event) {
    const known = {
      1001: "the server is shutting down",
      1006: "the connection dropped",
      1013: "the server has too many clients",
      4001: "the server dropped this client (it fell behind)",
      4401: "the server refused the ticket",
    };
    const text = event.reason || known[event.code] || "the connection closed";
    return `${text} (code ${event.code})`;
  }

  /** Close the socket at once, without waiting for a closing handshake. */
  function dropSocket(reason) {
    const ws = hmi.ws;
    hmi.ws = null;
    if (ws) {
      ws.onmessage = null;
      ws.onclose = null;
      ws.close();
    }
    if (reason) scheduleReconnect(reason);
  }

  function scheduleReconnect(reason) {
    if (!hmi.token) return;
    if (hmi.live) hmi.counters.disconnects += 1;
    setLive(false, "connection lost");
    hmi.attempts += 1;
    const base = Math.min(RECONNECT_MAX_MS, RECONNECT_FIRST_MS * 2 ** (hmi.attempts - 1));
    const delay = Math.round(base * (0.8 + Math.random() * 0.4));
    showBanner(`${reason}. Attempt ${hmi.attempts}, next try in ${(delay / 1000).toFixed(1)} s.`);
    clearTimeout(hmi.reconnectTimer);
    hmi.reconnectTimer = setTimeout(connect, delay);
  }

  /** Half-open connections: ping after silence, give up after a long one. */
  function watchdog() {
    if (!hmi.ws || !hmi.live) return;
    const silent = performance.now() - hmi.lastMessageMs;
    if (silent > WATCHDOG_DEAD_MS) dropSocket("no answer from the server");
    else if (silent > WATCHDOG_PING_MS) hmi.ws.send(JSON.stringify({ type: "ping" }));
  }

  function onMessage(message) {
    hmi.lastMessageMs = performance.now();
    hmi.counters.messages += 1;
    if (message.type === "snapshot") return onSnapshot(message);
    if (typeof message.seq === "number") checkSequence(message.seq);
    if (message.type === "state_changed") onStateChanged(message);
    else if (message.type === "progress") onProgress(message);
    else if (message.type === "error") onFault(message);
    else if (message.type === "alert") onAlert(message);
  }

  function onSnapshot(snapshot) {
    hmi.lastSeq = snapshot.seq;
    hmi.attempts = 0;
    hmi.counters.connects += 1;
    const progress = snapshot.operation && snapshot.operation.progress;
    if (snapshot.operation) startProgress(snapshot.operation.name, snapshot.operation.run_id);
    else if (hmi.progress && !hmi.progress.ended) hmi.progress.ended = "ended";
    if (progress) updateProgress(progress);
    setLive(true);
    applyState(snapshot);
    refreshPanels();
    refreshTrajectory();
  }

  /** seq rises by one; a gap means something was missed: resynchronise from GET /state. */
  function checkSequence(seq) {
    if (hmi.lastSeq !== null && seq !== hmi.lastSeq + 1) {
      hmi.counters.gaps += 1;
      getJson("/state").then(applyIfNewer).catch(() => {});
    }
    hmi.lastSeq = seq;
  }

  function onStateChanged(message) {
    const { old_state: from, new_state: to, event } = message;
    if (isOperational(to) && !isOperational(from) && to !== "PAUSED") startProgress(to, null);
    if (!isOperational(to) && hmi.progress && !hmi.progress.ended) {
      hmi.progress.ended = ENDINGS[event] || event.toLowerCase();
    }
    applyState(message.snapshot);
    refreshPanels();
    setTimeout(refreshPanels, 1000); // device figures settle a moment after a transition
    if (from === "CALIBRATING_ROBOT" || from === "CALIBRATING_CAMERA") refreshCalibration();
    if (isOperational(from) && !isOperational(to)) refreshFrame(); // it may have taken a picture
    if (from === "CREATING_WORKPIECE") refreshLibrary();
  }

  function onProgress(message) {
    if (message.recovery_attempt) {
      const outcome = message.recovered ? "recovered" : "failed";
      showMessage("info", `recovery attempt ${message.recovery_attempt} (${message.cause}): ${outcome}`);
      return;
    }
    if (!hmi.progress || hmi.progress.run_id !== message.run_id) {
      startProgress(message.operation, message.run_id);
    }
    updateProgress(message);
    if (message.operation === "trajectory" && hmi.trajectory?.run_id !== message.run_id) {
      refreshTrajectory();
    }
    renderProgress();
    drawTrajectory();
  }

  function onFault(fault) {
    showMessage("error", `fault ${fault.code} (${fault.component}): ${fault.message}`);
  }

  function onAlert(alert) {
    showMessage("error", `alert: ${alert.message}`);
  }

  /** Test and maintenance hook: close the socket as if the network dropped it. */
  function dropConnection() {
    dropSocket("closed by the page");
  }

  // --- state ----------------------------------------------------------------

  function isOperational(state) {
    return STATE_TONE[state] === "busy" || state === "PAUSED";
  }

  /** A state read over HTTP may race the socket: never step back to an older state. */
  function applyIfNewer(view) {
    if (!hmi.view || view.since >= hmi.view.since) applyState(view);
  }

  function applyState(view) {
    hmi.view = view;
    hmi.enteredAtMs = performance.now() - (view.time_in_state || 0) * 1000;
    renderState();
    renderCommands();
    renderProgress();
  }

  /** Live only while the socket is up and its snapshot applied; otherwise greyed, "not live". */
  function setLive(live, text) {
    hmi.live = live;
    $("link").dataset.live = String(live);
    $("link-text").textContent = live ? "live" : text || "not live";
    $("state").dataset.stale = String(!live);
    $("app").dataset.live = String(live);
    if (live) $("banner").hidden = true;
    renderCommands();
  }

  function showBanner(detail) {
    $("banner-detail").textContent = detail;
    $("banner").hidden = false;
  }

  function renderState() {
    const view = hmi.view;
    if (!view) return;
    const box = $("state");
    box.dataset.state = view.state;
    box.dataset.tone = STATE_TONE[view.state] || "init";
    $("state-name").textContent = view.state.replaceAll("_", " ");
    $("state-previous").textContent = view.previous_state
      ? `from ${view.previous_state.replaceAll("_", " ")}`
      : "";
    const op = view.operation;
    $("state-operation").textContent = op ? `operation ${op.name} · run ${op.run_id}` : "";
    renderFault(view);
    tick();
  }

  function renderFault(view) {
    const reason = view.state === "ERROR" ? view.stop_reason || view.error : null;
    $("fault").hidden = !reason;
    if (!reason) return;
    $("fault-message").textContent = reason.message;
    $("fault-meta").textContent =
      `${reason.code} · ${reason.component} · ${reason.classification} · ${clockTime(reason.time)}`;
    $("fault-action").textContent = reason.recommended_action || "—";
    const latest = view.error;
    const differs = latest && view.stop_reason && latest.event_id !== view.stop_reason.event_id;
    $("fault-latest").hidden = !differs;
    if (differs) $("fault-latest").textContent = `Latest fault: ${latest.code}: ${latest.message}`;
  }

  /** The clock, and the time in state: frozen while not live, as the state itself is. */
  function tick() {
    $("clock").textContent = new Date().toLocaleTimeString([], { hour12: false });
    if (!hmi.view || (!hmi.live && $("state-time").textContent !== "—")) return;
    const seconds = (performance.now() - hmi.enteredAtMs) / 1000;
    $("state-time").textContent = duration(seconds);
  }

  // --- commands -------------------------------------------------------------

  function renderCommands() {
    const allowed = new Set((hmi.view && hmi.view.available_commands) || []);
    for (const button of document.querySelectorAll("[data-command]")) {
      const name = button.dataset.command;
      button.disabled = !hmi.live || !allowed.has(name) || hmi.pending.has(name);
    }
  }

  async function sendCommand(name) {
    hmi.pending.add(name);
    renderCommands();
    try {
      const response = await api("POST", `/${name}`);
      showAnswer(response.status, await errorText(response));
    } catch (error) {
      if (!(error instanceof AuthError)) showMessage("error", `${name}: ${error.message}`);
    } finally {
      hmi.pending.delete(name);
      renderCommands();
    }
  }

  async function emergencyStop() {
    try {
      const response = await api("POST", "/estop", { reason: "STOP pressed on the HMI" });
      showAnswer(response.status, await errorText(response));
    } catch (error) {
      if (!(error instanceof AuthError)) {
        showMessage("error", `STOP could not reach the server (${error.message}): use the e-stop`);
      }
    }
  }

  function showAnswer(status, text) {
    const kind = status === 202 ? "ok" : status === 409 ? "refused" : "error";
    showMessage(kind, `${status}: ${text}`);
  }

  function showMessage(kind, text) {
    const box = $("message");
    box.hidden = false;
    box.dataset.kind = kind;
    box.textContent = `${clockTime(Date.now() / 1000)}  ${text}`;
  }

  // --- progress -------------------------------------------------------------

  function startProgress(operation, runId) {
    hmi.progress = { operation, run_id: runId, waypoint: 0, of: 0, fraction: 0, ended: null };
  }

  function updateProgress(update) {
    const progress = hmi.progress;
    if (!progress) return;
    if (update.run_id) progress.run_id = update.run_id;
    for (const key of ["waypoint", "of", "fraction", "workpiece", "step", "views"]) {
      if (update[key] !== undefined) progress[key] = update[key];
    }
  }

  function renderProgress() {
    const progress = hmi.progress;
    const bar = $("progress");
    const fraction = progress ? Math.max(0, Math.min(1, progress.fraction || 0)) : 0;
    bar.setAttribute("aria-valuenow", String(Math.round(fraction * 100)));
    bar.dataset.waypoint = String(progress?.waypoint || 0);
    bar.dataset.of = String(progress?.of || 0);
    bar.dataset.ended = progress?.ended ? "true" : "false";
    $("progress-fill").style.width = `${(fraction * 100).toFixed(1)}%`;
    $("progress-label").textContent = progressLabel(progress, fraction);
    $("progress-workpiece").textContent = progress?.workpiece || "—";
    $("progress-run").textContent = progress?.run_id ? `run ${progress.run_id}` : "";
    $("progress-note").textContent = progress?.ended ? `last run ${progress.ended}` : "";
  }

  function progressLabel(progress, fraction) {
    if (!progress) return "no operation";
    const percent = `${Math.round(fraction * 100)} %`;
    if (progress.waypoint) return `waypoint ${progress.waypoint} of ${progress.of} · ${percent}`;
    if (progress.views !== undefined) return `view ${progress.views} of ${progress.of} · ${percent}`;
    if (progress.step) return `${progress.step} · ${percent}`;
    return "starting…";
  }

  // --- periodic panels ------------------------------------------------------

  let refreshing = false;
  let refreshAgain = false;

  /** Health, KPIs and history; a request during a refresh runs once it is done. */
  async function refreshPanels() {
    if (!hmi.token) return;
    if (refreshing) {
      refreshAgain = true;
      return;
    }
    refreshing = true;
    try {
      do {
        refreshAgain = false;
        await Promise.all([
          panel("card-health", "/health", renderHealth),
          panel("card-kpis", "/kpis", renderKpis),
          panel("card-history", `/history?limit=${HISTORY_ROWS}`, renderHistory),
        ]);
      } while (refreshAgain && hmi.token);
    } finally {
      refreshing = false;
    }
  }

  async function panel(cardClass, path, render) {
    const card = document.querySelector(`.${cardClass}`);
    try {
      render(await getJson(path));
      card.dataset.stale = "false";
    } catch {
      card.dataset.stale = "true";
    }
  }

  function renderHealth(health) {
    const status = $("health-status");
    status.textContent = health.status;
    status.dataset.kind = health.status === "ok" ? "ok" : "fault";
    const devices = $("devices");
    devices.replaceChildren(
      ...["robot", "glue", "camera"]
        .filter((name) => health.devices[name])
        .map((name) => deviceCard(name, health.devices[name])),
    );
  }

  function deviceCard(name, device) {
    const card = element("div", "device");
    card.dataset.device = name;
    card.dataset.connected = String(device.connected);
    const state = element("span", "pill", device.connected ? "connected" : "disconnected");
    state.dataset.kind = device.connected ? "ok" : "fault";
    const head = element("div", "device-head");
    head.append(element("span", "device-name", name), state);
    card.append(head, facts(deviceFacts(name, device)));
    if (device.last_error) card.append(element("div", "device-error", device.last_error));
    return card;
  }

  function deviceFacts(name, device) {
    const rtt = device.last_rtt_ms == null ? "—" : `${number(device.last_rtt_ms, 1)} ms`;
    const rows = [["round trip", rtt]];
    if (name === "robot") {
      rows.push(
        ["link losses", String(device.connection_losses ?? "—")],
        ["reconnects", String(device.reconnects ?? "—")],
      );
    } else if (name === "glue") {
      const alarms = (device.alarms || []).join(", ");
      rows.push(
        ["flow", `${number(device.flow_ml_min, 1)} ml/min`],
        ["pressure", `${number(device.pressure_psi, 1)} psi`],
        ["temperature", `${number(device.temperature_c, 1)} °C`],
        ["valve", device.valve_open ? "OPEN" : "closed", device.valve_open ? "on" : ""],
        ["alarms", alarms || "none", alarms ? "alarm" : ""],
      );
    } else if (name === "camera") {
      rows.push(["resolution", device.resolution || "—"], ["mode", device.mode || "—"]);
    }
    return rows;
  }

  function renderKpis(kpis) {
    const oee = kpis.oee || {};
    const figures = [
      ["OEE", percent(oee.oee)],
      ["Availability", percent(oee.availability)],
      ["Utilization", percent(kpis.utilization)],
      ["Workpieces", String(kpis.workpieces_processed ?? "—")],
      ["Failed", String(kpis.workpieces_failed ?? "—")],
      ["Operations", String(kpis.operations_completed ?? "—")],
      ["MTBF", kpis.mtbf_s == null ? "—" : duration(kpis.mtbf_s)],
      ["MTTR", kpis.mttr_s == null ? "—" : duration(kpis.mttr_s)],
      ["Errors", String(kpis.errors_counted ?? "—")],
    ];
    $("kpis").replaceChildren(
      ...figures.map(([label, value]) => {
        const tile = element("div", "kpi");
        tile.dataset.kpi = label.toLowerCase();
        tile.append(element("div", "kpi-value", value), element("div", "kpi-label", label));
        return tile;
      }),
    );
    $("kpi-window").textContent = kpis.window ? `last ${number(kpis.window.hours, 0)} h` : "";
  }

  function renderHistory(page) {
    const rows = (page.transitions || []).slice(0, HISTORY_ROWS).map((t) => {
      const row = document.createElement("tr");
      for (const [text, cls] of [
        [clockTime(t.time), ""],
        [t.old_state, `tone-${STATE_TONE[t.old_state] || "init"}`],
        [t.new_state, `tone-${STATE_TONE[t.new_state] || "init"}`],
        [t.event, ""],
        [duration(t.time_in_old_state), "num"],
      ]) {
        row.append(element("td", cls, text));
      }
      return row;
    });
    $("history").replaceChildren(...rows);
  }

  async function refreshLibrary() {
    try {
      const { workpieces } = await getJson("/workpieces");
      const urls = await Promise.all(
        workpieces.map((w) => (w.has_thumbnail ? blobUrl(`/workpieces/${encodeURIComponent(w.id)}/thumbnail`) : null)),
      );
      hmi.thumbnails.forEach((url) => URL.revokeObjectURL(url));
      hmi.thumbnails = urls.filter(Boolean);
      $("library").replaceChildren(...workpieces.map((w, i) => workpieceCard(w, urls[i])));
      $("library-count").textContent = `${workpieces.length} in the library`;
    } catch (error) {
      if (!(error instanceof AuthError)) $("library-count").textContent = "library unavailable";
    }
  }

  function workpieceCard(workpiece, url) {
    const card = element("figure", "workpiece");
    card.dataset.workpiece = workpiece.id;
    const picture = url ? document.createElement("img") : element("div", "no-thumb", "no image");
    if (url) {
      picture.src = url;
      picture.alt = `thumbnail of ${workpiece.name}`;
    }
    const spray = workpiece.spray || {};
    const caption = element("figcaption");
    caption.append(
      element("strong", "", workpiece.name),
      element("span", "muted small", `${workpiece.id} · fill ${spray.fill || "—"} · ${spray.speed_mm_s ?? "—"} mm/s`),
    );
    card.append(picture, caption);
    return card;
  }

  // --- trajectory -----------------------------------------------------------

  async function refreshTrajectory() {
    const previousRun = hmi.trajectory?.run_id;
    try {
      const response = await api("GET", "/trajectory");
      hmi.trajectory = response.ok ? await response.json() : null;
      const reached = hmi.trajectory?.waypoint;
      if (reached && hmi.progress && hmi.progress.run_id === hmi.trajectory.run_id) {
        hmi.progress.waypoint = Math.max(hmi.progress.waypoint || 0, reached);
      }
    } catch {
      /* keep the last one */
    }
    // A new plan: its run has just looked at the table (with contour matching).
    if (hmi.trajectory && hmi.trajectory.run_id !== previousRun) refreshFrame();
    renderTrajectoryInfo();
    drawTrajectory();
  }

  function renderTrajectoryInfo() {
    const path = hmi.trajectory?.planned_path || [];
    const plan = hmi.trajectory
      ? `run ${hmi.trajectory.run_id} · ${path.length} waypoints`
      : "no trajectory planned yet";
    const info = hmi.frameInfo;
    let over = "";
    if (hmi.frame && info) over = ` · camera ${clockTime(info.time)} (${info.source.replace(/_/g, " ")})`;
    else if (hmi.calibrationImage) over = " · calibration image";
    $("trajectory-info").textContent = plan + over;
  }

  async function refreshCalibration() {
    try {
      hmi.calibration = await getJson("/calibration");
      const url = hmi.calibration?.robot?.has_image ? await blobUrl("/calibration/image") : null;
      if (url) hmi.calibrationImage = await loadImage(url);
    } catch {
      /* the path is drawn without a background */
    }
    renderTrajectoryInfo();
    drawTrajectory();
  }

  /** The latest frame an operation captured (GET /camera/frame, 404 until one did). */
  async function refreshFrame() {
    try {
      const response = await api("GET", "/camera/frame");
      if (!response.ok) return; // none yet: the calibration image stands in
      const info = {
        time: Number(response.headers.get("X-Frame-Time")),
        source: response.headers.get("X-Frame-Source") || "",
        run: response.headers.get("X-Frame-Run-Id") || "",
      };
      const shown = hmi.frameInfo;
      if (shown && info.time <= shown.time) return; // the same one, or an answer overtaken
      const image = await loadImage(URL.createObjectURL(await response.blob()));
      if (!image || (hmi.frameInfo && info.time <= hmi.frameInfo.time)) return;
      hmi.frame = image;
      hmi.frameInfo = info;
    } catch {
      return; /* keep the last one */
    }
    renderTrajectoryInfo();
    drawTrajectory();
  }

  function loadImage(url) {
    return new Promise((resolve) => {
      const image = new Image();
      image.onload = () => {
        URL.revokeObjectURL(url);
        resolve(image);
      };
      image.onerror = () => resolve(null);
      image.src = url;
    });
  }

  /** Table mm → image px: the inverse of the calibration's image → robot homography. */
  function tableToImage() {
    const h = hmi.calibration?.robot?.homography;
    const inverse = h && invert3(h);
    if (!inverse) return null;
    return ([x, y]) => {
      const w = inverse[2][0] * x + inverse[2][1] * y + inverse[2][2];
      return [
        (inverse[0][0] * x + inverse[0][1] * y + inverse[0][2]) / w,
        (inverse[1][0] * x + inverse[1][1] * y + inverse[1][2]) / w,
      ];
    };
  }

  function invert3(m) {
    const [[a, b, c], [d, e, f], [g, h, i]] = m;
    const A = e * i - f * h, B = -(d * i - f * g), C = d * h - e * g;
    const det = a * A + b * B + c * C;
    if (!det) return null;
    return [
      [A / det, -(b * i - c * h) / det, (b * f - c * e) / det],
      [B / det, (a * i - c * g) / det, -(a * f - c * d) / det],
      [C / det, -(a * h - b * g) / det, (a * e - b * d) / det],
    ];
  }

  function fitCanvas(canvas) {
    const box = canvas.parentElement.getBoundingClientRect();
    const ratio = window.devicePixelRatio || 1;
    const width = Math.max(1, Math.round(box.width));
    const height = Math.max(1, Math.round(box.height));
    if (canvas.width !== width * ratio || canvas.height !== height * ratio) {
      canvas.width = width * ratio;
      canvas.height = height * ratio;
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    return { ctx, width, height };
  }

  function boundingBox(points) {
    const xs = points.map((p) => p[0]);
    const ys = points.map((p) => p[1]);
    const x = Math.min(...xs), y = Math.min(...ys);
    return { x, y, w: Math.max(...xs) - x, h: Math.max(...ys) - y };
  }

  /** A window of the image around the path, in the canvas's aspect ratio, inside the image. */
  function viewWindow(box, aspect, imageW, imageH) {
    let w = Math.max(box.w * 2.4, box.h * 2.4 * aspect, 240);
    let h = w / aspect;
    if (w > imageW) [w, h] = [imageW, imageW / aspect];
    if (h > imageH) [w, h] = [imageH * aspect, imageH];
    const cx = box.x + box.w / 2, cy = box.y + box.h / 2;
    const x = Math.min(Math.max(cx - w / 2, 0), imageW - w);
    const y = Math.min(Math.max(cy - h / 2, 0), imageH - h);
    return { x, y, w, h };
  }

  function drawTrajectory() {
    const { ctx, width, height } = fitCanvas($("trajectory-canvas"));
    ctx.fillStyle = "#10151b";
    ctx.fillRect(0, 0, width, height);
    const path = hmi.trajectory?.planned_path || [];
    const project = projection(ctx, path, width, height);
    if (!path.length || !project) {
      return caption(ctx, width, height, "no trajectory planned since the server started");
    }
    const points = path.map((w) => project(w.pose));
    const reached = Math.min(currentWaypoint(), path.length);
    drawSegments(ctx, path, points, 0, path.length, false);
    drawSegments(ctx, path, points, 0, reached, true);
    points.forEach((p) => dot(ctx, p, 2.5, "rgba(230,238,245,0.8)"));
    if (reached > 0) dot(ctx, points[reached - 1], 8, "#ffffff", "#2f8cff");
  }

  function currentWaypoint() {
    const progress = hmi.progress;
    if (!progress || progress.run_id !== hmi.trajectory?.run_id) return 0;
    return progress.waypoint || 0;
  }

  /** mm → canvas: over the camera frame through the calibration, else by the path's own box.
   * The latest frame an operation captured, else the robot calibration's own image. */
  function projection(ctx, path, width, height) {
    const toImage = tableToImage();
    const frame = hmi.frame || hmi.calibrationImage;
    const canvas = $("trajectory-canvas");
    canvas.dataset.background = "none";
    if (frame) canvas.dataset.background = hmi.frame ? "camera" : "calibration";
    if (frame && !path.length) {
      drawContained(ctx, frame, width, height);
      return null;
    }
    if (frame && !toImage) canvas.dataset.background = "none";
    if (frame && toImage) {
      const inImage = path.map((w) => toImage(w.pose));
      const { naturalWidth: imageW, naturalHeight: imageH } = frame;
      const box = viewWindow(boundingBox(inImage), width / height, imageW, imageH);
      ctx.drawImage(frame, box.x, box.y, box.w, box.h, 0, 0, width, height);
      return (pose) => {
        const [u, v] = toImage(pose);
        return [((u - box.x) * width) / box.w, ((v - box.y) * height) / box.h];
      };
    }
    if (!path.length) return null;
    const box = boundingBox(path.map((w) => w.pose));
    const margin = 40;
    const scale = Math.min((width - 2 * margin) / (box.w || 1), (height - 2 * margin) / (box.h || 1));
    const ox = (width - box.w * scale) / 2, oy = (height - box.h * scale) / 2;
    drawGrid(ctx, width, height);
    return ([x, y]) => [ox + (x - box.x) * scale, height - (oy + (y - box.y) * scale)];
  }

  /** The whole frame, letterboxed, undistorted in shape. */
  function drawContained(ctx, image, width, height) {
    const scale = Math.min(width / image.naturalWidth, height / image.naturalHeight);
    const w = image.naturalWidth * scale, h = image.naturalHeight * scale;
    ctx.drawImage(image, (width - w) / 2, (height - h) / 2, w, h);
  }

  function drawSegments(ctx, path, points, from, to, done) {
    ctx.lineCap = "round";
    ctx.lineJoin = "round";
    for (let i = Math.max(1, from); i < to; i += 1) {
      const spray = path[i].spray;
      ctx.beginPath();
      ctx.moveTo(...points[i - 1]);
      ctx.lineTo(...points[i]);
      ctx.setLineDash(spray || done ? [] : [6, 6]);
      ctx.lineWidth = done ? 6 : spray ? 4 : 2;
      ctx.strokeStyle = done ? DONE_COLOUR : spray ? "rgba(86,180,255,0.95)" : "rgba(200,210,220,0.7)";
      ctx.stroke();
    }
    ctx.setLineDash([]);
  }

  function drawGrid(ctx, width, height) {
    ctx.strokeStyle = "rgba(255,255,255,0.05)";
    ctx.lineWidth = 1;
    for (let x = 0; x < width; x += 40) line(ctx, [x, 0], [x, height]);
    for (let y = 0; y < height; y += 40) line(ctx, [0, y], [width, y]);
  }

  function line(ctx, a, b) {
    ctx.beginPath();
    ctx.moveTo(...a);
    ctx.lineTo(...b);
    ctx.stroke();
  }

  function dot(ctx, [x, y], radius, fill, stroke) {
    ctx.beginPath();
    ctx.arc(x, y, radius, 0, 2 * Math.PI);
    ctx.fillStyle = fill;
    ctx.fill();
    if (stroke) {
      ctx.lineWidth = 3;
      ctx.strokeStyle = stroke;
      ctx.stroke();
    }
  }

  function caption(ctx, width, height, text) {
    ctx.fillStyle = "rgba(0,0,0,0.55)";
    ctx.fillRect(0, height / 2 - 22, width, 44);
    ctx.fillStyle = "#c9d3dd";
    ctx.font = "16px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    ctx.fillText(text, width / 2, height / 2);
  }

  // --- small helpers --------------------------------------------------------

  function element(tag, className, text) {
    const node = document.createElement(tag);
    if (className) node.className = className;
    if (text !== undefined) node.textContent = text;
    return node;
  }

  function facts(rows) {
    const list = element("dl", "facts");
    for (const [term, value, mark] of rows) {
      const item = element("div", `fact ${mark || ""}`.trim());
      item.append(element("dt", "", term), element("dd", "", value));
      list.append(item);
    }
    return list;
  }

  function number(value, digits) {
    return typeof value === "number" ? value.toFixed(digits) : "—";
  }

  function percent(value) {
    return typeof value === "number" ? `${(value * 100).toFixed(1)} %` : "—";
  }

  function duration(seconds) {
    if (typeof seconds !== "number" || !isFinite(seconds)) return "—";
    const s = Math.max(0, Math.floor(seconds));
    const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), rest = s % 60;
    const two = (n) => String(n).padStart(2, "0");
    return h ? `${h}:${two(m)}:${two(rest)}` : `${two(m)}:${two(rest)}`;
  }

  function clockTime(unixSeconds) {
    if (typeof unixSeconds !== "number") return "—";
    return new Date(unixSeconds * 1000).toLocaleTimeString([], { hour12: false });
  }

  // --- start ----------------------------------------------------------------

  function init() {
    $("login-form").addEventListener("submit", onLogin);
    $("logout").addEventListener("click", () => signOut(""));
    $("estop").addEventListener("click", emergencyStop);
    for (const button of document.querySelectorAll("[data-command]")) {
      button.addEventListener("click", () => sendCommand(button.dataset.command));
    }
    window.addEventListener("resize", drawTrajectory);
    const token = sessionStorage.getItem(TOKEN_KEY);
    if (token) startSession(token, null);
    else showLogin("");
  }

  window.hmi = {
    dropConnection,
    status: () => ({
      live: hmi.live,
      state: hmi.view?.state ?? null,
      attempts: hmi.attempts,
      ...hmi.counters,
    }),
  };

  init();
})();

/*
 * PoseMatch setup page.
 *
 * The flow, in the order an engineer works:
 *   1. Load a camera frame (#frame-file, or drop a file on #frame-area). The file's own bytes
 *      are kept as loaded: they are what POST /v1/match receives. The browser decodes them only
 *      to show the frame on #frame-canvas at its natural pixel size.
 *   2. Drag a box on #overlay-canvas (or type it into #sel-x/#sel-y/#sel-w/#sel-h). "Register the
 *      box" cuts it out of the frame at natural resolution, encodes it as PNG and sends it to
 *      POST /v1/templates; "Register the file" sends a template image file as it is.
 *   3. The template list (GET /v1/templates, followed page by page) shows each template with a
 *      checkbox, a thumbnail (GET /v1/templates/{id}?includeImage=true) and a Delete button.
 *   4. "Find the checked templates" sends the frame, the checked IDs and the search options to
 *      POST /v1/match; every pose is drawn on the overlay (rotated outline, u/v axes, label) and
 *      listed in #poses with the timings in #timings.
 *
 * All state lives in `state`; redraw() repaints the overlay from it (the poses of the last
 * match, then the selection box), so the two can change independently. The API speaks the
 * proto3 canonical JSON mapping: fields holding their default value (0, false, "", empty list)
 * are left out of responses, so every read below supplies the default itself.
 */
(function () {
  'use strict';

  // ---------------------------------------------------------------------------------------
  // Constants
  // ---------------------------------------------------------------------------------------

  const PAGE_SIZE = 100;              // templates per list page
  const MIN_TEMPLATE_SIDE = 4;        // the server needs at least 4 px per side
  const MAX_TEMPLATES_PER_MATCH = 16; // the server accepts 1..16 template IDs per match
  const THUMBNAIL_CONCURRENCY = 3;    // thumbnail requests in flight at once
  const TOKEN_KEY = 'posematch.token';

  // Outline colours, one per template of a match (dark enough for white label text); beyond
  // the list, colours are spread around the hue circle.
  const TEMPLATE_COLOURS = [
    '#1f5fbf', '#c15a00', '#7b3fb5', '#00838f',
    '#b0207a', '#5f6b00', '#8c564b', '#3d4b5c',
  ];
  const U_AXIS_COLOUR = '#ff4136'; // template +column direction
  const V_AXIS_COLOUR = '#2ecc40'; // template +row direction
  const SELECTION_COLOUR = '#ffd60a';
  const HALO_COLOUR = 'rgba(0, 0, 0, 0.6)';
  const LABEL_FONT = 'system-ui, -apple-system, "Segoe UI", Roboto, Arial, sans-serif';

  // ---------------------------------------------------------------------------------------
  // Elements and state
  // ---------------------------------------------------------------------------------------

  const byId = (id) => document.getElementById(id);

  const el = {
    token: byId('token'),
    frameFile: byId('frame-file'),
    frameArea: byId('frame-area'),
    frameHint: byId('frame-hint'),
    canvasStack: byId('canvas-stack'),
    frameCanvas: byId('frame-canvas'),
    overlay: byId('overlay-canvas'),
    frameInfo: byId('frame-info'),
    pointerInfo: byId('pointer-info'),
    selX: byId('sel-x'),
    selY: byId('sel-y'),
    selW: byId('sel-w'),
    selH: byId('sel-h'),
    selectionInfo: byId('selection-info'),
    clearSelection: byId('clear-selection'),
    templateId: byId('template-id'),
    templateLabels: byId('template-labels'),
    replace: byId('replace'),
    registerSelection: byId('register-selection'),
    templateFile: byId('template-file'),
    registerFile: byId('register-file'),
    refreshTemplates: byId('refresh-templates'),
    templatesInfo: byId('templates-info'),
    templates: byId('templates'),
    maxInstances: byId('max-instances'),
    minScore: byId('min-score'),
    angleStart: byId('angle-start'),
    angleExtent: byId('angle-extent'),
    scaleMin: byId('scale-min'),
    scaleMax: byId('scale-max'),
    polarity: byId('polarity'),
    method: byId('method'),
    timeoutMs: byId('timeout-ms'),
    noRefine: byId('no-refine'),
    suppressAcross: byId('suppress-across'),
    runMatch: byId('run-match'),
    timings: byId('timings'),
    posesCaption: byId('poses-caption'),
    posesBody: byId('poses-body'),
    status: byId('status'),
  };
  const selectionInputs = [el.selX, el.selY, el.selW, el.selH];

  const state = {
    frame: null,          // {name, bytes: ArrayBuffer, width, height, base64: string|null}
    frameSeq: 0,          // increases with every frame load, to drop stale decodes
    selection: null,      // {x, y, w, h}: integer image pixels, or null
    drag: null,           // {pointerId, x0, y0} while the pointer draws a box
    templates: new Map(), // templateId -> TemplateInfo (without the image)
    checked: new Set(),   // checked template IDs, kept across list refreshes
    listGeneration: 0,    // increases with every list refresh, to drop stale ones
    thumbnails: new Map(),// thumbnailKey(info) -> data: URL
    match: null,          // {poses: [normalised pose], sizes: Map id -> {width, height}}
    highlighted: -1,      // index of the pose highlighted from the table, or -1
  };

  // ---------------------------------------------------------------------------------------
  // Small helpers
  // ---------------------------------------------------------------------------------------

  /** An HTTP/API failure: `status` 0 when the server could not be reached. */
  class ApiError extends Error {
    constructor(status, code, message) {
      super(message);
      this.name = 'ApiError';
      this.status = status;
      this.code = code;
    }
  }

  /** Something the user has to fix in a field (`field` gets the focus). */
  class InputError extends Error {
    constructor(message, field) {
      super(message);
      this.name = 'InputError';
      this.field = field || null;
    }
  }

  /** A JSON number (or numeric string, as int64 values are) with 0 for absent/invalid. */
  const num = (value) => {
    const n = Number(value);
    return Number.isFinite(n) ? n : 0;
  };
  const clamp = (value, lo, hi) => Math.min(Math.max(value, lo), hi);
  const plural = (n, word) => `${n} ${word}${n === 1 ? '' : 's'}`;
  /** Resolves after the browser had a chance to paint (or after 50 ms in a hidden tab). */
  const nextPaint = () => new Promise((resolve) => {
    setTimeout(resolve, 50);
    requestAnimationFrame(() => setTimeout(resolve, 0));
  });

  function formatBytes(n) {
    if (n < 1024) return `${n} B`;
    if (n < 1024 * 1024) return `${(n / 1024).toFixed(1)} KiB`;
    return `${(n / (1024 * 1024)).toFixed(1)} MiB`;
  }

  /** The text of a control's label: names the field in validation messages. */
  function fieldName(input) {
    const label = input.labels && input.labels[0];
    return label ? label.textContent.trim() : input.id;
  }

  /**
   * Base64 of binary data, encoded in slices so that frames of tens of MB neither overflow
   * the argument list of String.fromCharCode nor build one huge binary string. The slice
   * length is a multiple of 3, so the slices' encodings simply concatenate.
   */
  function bytesToBase64(data) {
    const bytes = data instanceof Uint8Array ? data : new Uint8Array(data);
    const SLICE = 0x8000 - (0x8000 % 3); // 32766 bytes: about 32 KiB
    const parts = [];
    for (let i = 0; i < bytes.length; i += SLICE) {
      parts.push(btoa(String.fromCharCode.apply(null, bytes.subarray(i, i + SLICE))));
    }
    return parts.join('');
  }

  /** Copy of a TemplateInfo without its (possibly large) image. */
  function withoutImage(info) {
    const copy = Object.assign({}, info);
    delete copy.image;
    delete copy.mask;
    return copy;
  }

  function rememberTemplate(info) {
    if (info && info.templateId) state.templates.set(info.templateId, withoutImage(info));
  }

  function templateColour(i) {
    return i < TEMPLATE_COLOURS.length
      ? TEMPLATE_COLOURS[i]
      : `hsl(${Math.round((i * 137.508) % 360)}, 65%, 38%)`;
  }

  // ---------------------------------------------------------------------------------------
  // Status area
  // ---------------------------------------------------------------------------------------

  /** Shows progress or a result; `isError` marks it as an error (class "error"). */
  function setStatus(message, isError = false) {
    el.status.textContent = message;
    el.status.classList.toggle('error', isError);
  }

  /** Shows a failure of `action` ("Registering failed", ...) with a hint where one helps. */
  function reportError(action, err) {
    if (err instanceof InputError) {
      setStatus(err.message, true);
      if (err.field) {
        err.field.setAttribute('aria-invalid', 'true');
        err.field.focus();
      }
      return;
    }
    console.error(action, err);
    let message = (err && err.message) || String(err);
    if (err instanceof ApiError) {
      if (err.status === 409 || err.code === 'ALREADY_EXISTS') {
        message += ' (tick "Replace if it exists" to overwrite it)';
      } else if (err.status === 401 || err.code === 'UNAUTHENTICATED') {
        message += ' (check the bearer token)';
      }
    }
    setStatus(action ? `${action}: ${message}` : message, true);
  }

  /**
   * Runs `task` with `buttons` disabled, so a request cannot be sent twice; gives the focus
   * back to the button that had it (disabling a button drops its focus).
   */
  async function withBusyButtons(buttons, task) {
    const focused = buttons.find((button) => button === document.activeElement) || null;
    for (const button of buttons) {
      button.disabled = true;
      button.setAttribute('aria-busy', 'true');
    }
    try {
      return await task();
    } finally {
      for (const button of buttons) {
        button.disabled = false;
        button.removeAttribute('aria-busy');
      }
      if (focused && (!document.activeElement || document.activeElement === document.body)) {
        focused.focus();
      }
    }
  }

  // ---------------------------------------------------------------------------------------
  // API
  // ---------------------------------------------------------------------------------------

  /**
   * One JSON request to the API. Sends the bearer token when one is set. Resolves to the
   * parsed body ({} when empty); rejects with an ApiError carrying the server's `message`
   * (or the HTTP status text when the error body is not JSON).
   */
  async function api(method, path, body) {
    const headers = { Accept: 'application/json' };
    const token = el.token.value.trim();
    if (token) {
      if (/[^\x21-\x7e]/.test(token)) {
        throw new InputError('The bearer token has characters that cannot be sent in an HTTP header.', null);
      }
      headers.Authorization = `Bearer ${token}`;
    }
    const init = { method, headers, cache: 'no-store' };
    if (body !== undefined) {
      headers['Content-Type'] = 'application/json';
      init.body = JSON.stringify(body);
    }

    let response;
    let text;
    try {
      response = await fetch(path, init);
      text = await response.text();
    } catch (err) {
      throw new ApiError(0, 'NETWORK', `cannot reach the server: ${(err && err.message) || err}`);
    }

    let data = null;
    if (text) {
      try {
        data = JSON.parse(text);
      } catch (_) {
        data = null;
      }
    }
    if (!response.ok) {
      const message = data && typeof data.message === 'string' && data.message
        ? data.message
        : `${response.status} ${response.statusText || 'HTTP error'}`;
      throw new ApiError(response.status, (data && data.code) || '', message);
    }
    if (text && (data === null || typeof data !== 'object')) {
      throw new ApiError(response.status, 'BAD_RESPONSE', 'the server answered with something that is not JSON');
    }
    return data || {};
  }

  const templatePath = (id) => `/v1/templates/${encodeURIComponent(id)}`;

  // ---------------------------------------------------------------------------------------
  // Bearer token
  // ---------------------------------------------------------------------------------------

  function initToken() {
    try {
      el.token.value = sessionStorage.getItem(TOKEN_KEY) || '';
    } catch (_) {
      // Storage unavailable (privacy settings): the token just is not remembered.
    }
    const save = () => {
      try {
        sessionStorage.setItem(TOKEN_KEY, el.token.value);
      } catch (_) {
        // See above.
      }
    };
    el.token.addEventListener('input', save);
    el.token.addEventListener('change', () => {
      save();
      refreshTemplates();
    });
  }

  // ---------------------------------------------------------------------------------------
  // Camera frame
  // ---------------------------------------------------------------------------------------

  /** Decodes an image blob: an ImageBitmap where possible, else an <img>. */
  async function decodeImage(blob) {
    if (typeof createImageBitmap === 'function') {
      try {
        // Keep the stored pixel values: they are cut out into templates.
        return await createImageBitmap(blob, { colorSpaceConversion: 'none', premultiplyAlpha: 'none' });
      } catch (_) {
        // Unsupported options or format: try an <img> below.
      }
    }
    const url = URL.createObjectURL(blob);
    try {
      const img = new Image();
      img.src = url;
      await img.decode();
      return img;
    } finally {
      URL.revokeObjectURL(url);
    }
  }

  /** Loads a frame file: keeps its bytes, draws it at natural size, resets the last match. */
  async function loadFrame(file) {
    if (!file) return;
    const seq = ++state.frameSeq;
    setStatus(`Loading ${file.name}…`);

    let bytes;
    let picture;
    try {
      bytes = await file.arrayBuffer();
      picture = await decodeImage(file);
    } catch (err) {
      if (seq === state.frameSeq) {
        setStatus(`Cannot show ${file.name}: the browser could not decode it as an image (${(err && err.message) || err}).`, true);
      }
      return;
    }
    if (seq !== state.frameSeq) return; // a newer file was chosen meanwhile

    const width = picture.naturalWidth || picture.width;
    const height = picture.naturalHeight || picture.height;
    for (const canvas of [el.frameCanvas, el.overlay]) {
      canvas.width = width;
      canvas.height = height;
    }
    el.frameCanvas.getContext('2d').drawImage(picture, 0, 0);
    if (typeof picture.close === 'function') picture.close();

    state.frame = { name: file.name, bytes, width, height, base64: null };
    el.frameCanvas.dataset.frameWidth = String(width);
    el.frameCanvas.dataset.frameHeight = String(height);
    el.frameArea.classList.remove('is-empty');
    el.frameArea.classList.add('has-frame');
    el.frameHint.hidden = true;
    el.canvasStack.hidden = false;
    el.frameInfo.textContent = `${file.name}: ${width}x${height} px, ${formatBytes(bytes.byteLength)}.`;

    el.selX.max = String(width);
    el.selW.max = String(width);
    el.selY.max = String(height);
    el.selH.max = String(height);

    clearMatch();
    // A box drawn on the previous frame stays if it still fits (same camera, same part).
    if (state.selection) {
      state.selection = clampSelection(state.selection);
      if (state.selection.w === 0 || state.selection.h === 0) state.selection = null;
      writeSelectionInputs();
    }
    updateSelectionInfo();
    redraw();
    setStatus(`Loaded ${file.name} (${width}x${height})`);
  }

  function hasFiles(event) {
    return !!event.dataTransfer && Array.from(event.dataTransfer.types || []).includes('Files');
  }

  function isFileInput(target) {
    return target instanceof HTMLInputElement && target.type === 'file';
  }

  /** Drag-and-drop of a frame onto #frame-area. */
  function initDropZone() {
    const area = el.frameArea;
    for (const type of ['dragenter', 'dragover']) {
      area.addEventListener(type, (event) => {
        if (!hasFiles(event)) return;
        event.preventDefault();
        event.dataTransfer.dropEffect = 'copy';
        area.classList.add('dragover');
      });
    }
    area.addEventListener('dragleave', (event) => {
      if (!area.contains(event.relatedTarget)) area.classList.remove('dragover');
    });
    area.addEventListener('drop', (event) => {
      if (!hasFiles(event)) return;
      event.preventDefault();
      area.classList.remove('dragover');
      const files = Array.from(event.dataTransfer.files || []);
      const file = files.find((f) => f.type.startsWith('image/')) || files[0];
      if (file) loadFrame(file);
    });
    // A file dropped anywhere else would make the browser leave the page (and lose the work);
    // file inputs keep their own drop behaviour.
    for (const type of ['dragover', 'drop']) {
      window.addEventListener(type, (event) => {
        if (hasFiles(event) && !isFileInput(event.target)) event.preventDefault();
      });
    }
  }

  // ---------------------------------------------------------------------------------------
  // Selection box (image pixels; edges on integer pixel boundaries)
  // ---------------------------------------------------------------------------------------

  /** A box clamped to the frame, with integer coordinates. */
  function clampSelection(sel) {
    const x = Math.round(sel.x);
    const y = Math.round(sel.y);
    const w = Math.round(sel.w);
    const h = Math.round(sel.h);
    if (!state.frame) return { x: Math.max(x, 0), y: Math.max(y, 0), w: Math.max(w, 0), h: Math.max(h, 0) };
    const cx = clamp(x, 0, state.frame.width);
    const cy = clamp(y, 0, state.frame.height);
    return {
      x: cx,
      y: cy,
      w: clamp(w, 0, state.frame.width - cx),
      h: clamp(h, 0, state.frame.height - cy),
    };
  }

  /** The box typed into the four inputs, or null while one of them is empty or invalid. */
  function selectionFromInputs() {
    const values = selectionInputs.map((input) => (input.value.trim() === '' ? NaN : Number(input.value)));
    if (values.some((v) => !Number.isFinite(v))) return null;
    return clampSelection({ x: values[0], y: values[1], w: values[2], h: values[3] });
  }

  function writeSelectionInputs() {
    const sel = state.selection;
    el.selX.value = sel ? String(sel.x) : '';
    el.selY.value = sel ? String(sel.y) : '';
    el.selW.value = sel ? String(sel.w) : '';
    el.selH.value = sel ? String(sel.h) : '';
  }

  function updateSelectionInfo() {
    const sel = state.selection;
    if (!sel || sel.w === 0 || sel.h === 0) {
      el.selectionInfo.textContent = 'No box yet.';
    } else if (sel.w < MIN_TEMPLATE_SIDE || sel.h < MIN_TEMPLATE_SIDE) {
      el.selectionInfo.textContent = `Box ${sel.w}x${sel.h} px: too small, a template needs at least ${MIN_TEMPLATE_SIDE} px per side.`;
    } else {
      el.selectionInfo.textContent = `Box ${sel.w}x${sel.h} px at (${sel.x}, ${sel.y}).`;
    }
  }

  /** Pointer position in image pixels (unrounded), from the displayed size of the overlay. */
  function imagePoint(event) {
    const rect = el.overlay.getBoundingClientRect();
    const sx = rect.width > 0 ? el.overlay.width / rect.width : 1;
    const sy = rect.height > 0 ? el.overlay.height / rect.height : 1;
    return { x: (event.clientX - rect.left) * sx, y: (event.clientY - rect.top) * sy };
  }

  /** The nearest pixel boundary inside the frame. */
  function snapPoint(point) {
    return {
      x: clamp(Math.round(point.x), 0, state.frame.width),
      y: clamp(Math.round(point.y), 0, state.frame.height),
    };
  }

  function onPointerDown(event) {
    if (!state.frame || event.button !== 0 || state.drag) return;
    event.preventDefault();
    el.overlay.setPointerCapture(event.pointerId);
    const p = snapPoint(imagePoint(event));
    state.drag = { pointerId: event.pointerId, x0: p.x, y0: p.y };
    state.selection = { x: p.x, y: p.y, w: 0, h: 0 };
    writeSelectionInputs();
    updateSelectionInfo();
    redraw();
  }

  function dragTo(event) {
    const p = snapPoint(imagePoint(event));
    const { x0, y0 } = state.drag;
    state.selection = clampSelection({
      x: Math.min(x0, p.x),
      y: Math.min(y0, p.y),
      w: Math.abs(p.x - x0),
      h: Math.abs(p.y - y0),
    });
    writeSelectionInputs();
    updateSelectionInfo();
    redraw();
  }

  function onPointerMove(event) {
    if (state.frame) {
      const p = imagePoint(event);
      el.pointerInfo.textContent = `Pointer at (${Math.floor(p.x)}, ${Math.floor(p.y)}).`;
    }
    if (state.drag && event.pointerId === state.drag.pointerId) dragTo(event);
  }

  function onPointerEnd(event) {
    if (!state.drag || event.pointerId !== state.drag.pointerId) return;
    if (event.type === 'pointerup') dragTo(event);
    state.drag = null;
    if (el.overlay.hasPointerCapture(event.pointerId)) el.overlay.releasePointerCapture(event.pointerId);
    // A click without a drag clears the box.
    if (state.selection && (state.selection.w === 0 || state.selection.h === 0)) {
      state.selection = null;
      writeSelectionInputs();
    }
    updateSelectionInfo();
    redraw();
  }

  function initSelection() {
    el.overlay.addEventListener('pointerdown', onPointerDown);
    el.overlay.addEventListener('pointermove', onPointerMove);
    el.overlay.addEventListener('pointerup', onPointerEnd);
    el.overlay.addEventListener('pointercancel', onPointerEnd);
    el.overlay.addEventListener('pointerleave', () => {
      if (!state.drag) el.pointerInfo.textContent = '';
    });

    for (const input of selectionInputs) {
      // While typing: redraw the (clamped) box without rewriting what is being typed.
      input.addEventListener('input', () => {
        state.selection = selectionFromInputs();
        updateSelectionInfo();
        redraw();
      });
      // When done: show the clamped values.
      input.addEventListener('change', () => {
        state.selection = selectionFromInputs();
        if (state.selection) writeSelectionInputs();
        updateSelectionInfo();
        redraw();
      });
    }

    el.clearSelection.addEventListener('click', () => {
      state.selection = null;
      writeSelectionInputs();
      updateSelectionInfo();
      redraw();
    });

    // The overlay's line widths and label sizes follow its displayed size.
    if (typeof ResizeObserver === 'function') {
      new ResizeObserver(() => redraw()).observe(el.overlay);
    } else {
      window.addEventListener('resize', () => redraw());
    }
  }

  // ---------------------------------------------------------------------------------------
  // Overlay drawing
  // ---------------------------------------------------------------------------------------

  /** Image pixels per CSS pixel of the displayed overlay (>= 1 as the frame is never enlarged). */
  function displayScale() {
    const rect = el.overlay.getBoundingClientRect();
    return rect.width > 0 ? el.overlay.width / rect.width : 1;
  }

  /** Repaints the overlay: the poses of the last match, then the selection box. */
  function redraw() {
    const canvas = el.overlay;
    const ctx = canvas.getContext('2d');
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!state.frame) return;
    const s = displayScale();

    if (state.match) {
      const { poses } = state.match;
      poses.forEach((pose, i) => {
        if (i !== state.highlighted) drawPose(ctx, pose, false, s);
      });
      if (poses[state.highlighted]) drawPose(ctx, poses[state.highlighted], true, s);
    }
    if (state.selection) drawSelection(ctx, state.selection, s);
  }

  /**
   * Maps template (column, row) to canvas coordinates. The transform works with pixel centres
   * at integer coordinates (OpenCV convention); a canvas has pixel centres at +0.5.
   */
  function toCanvas(t, col, row) {
    return [t[0] * col + t[1] * row + t[2] + 0.5, t[3] * col + t[4] * row + t[5] + 0.5];
  }

  /** Strokes the current path in `colour` over a dark halo, so it shows on any background. */
  function strokeWithHalo(ctx, colour, width, s) {
    ctx.strokeStyle = HALO_COLOUR;
    ctx.lineWidth = width + 2 * s;
    ctx.stroke();
    ctx.strokeStyle = colour;
    ctx.lineWidth = width;
    ctx.stroke();
  }

  /** A line from `from` to `to` with a filled arrow head at `to`. */
  function drawArrow(ctx, from, to, colour, s) {
    const dx = to[0] - from[0];
    const dy = to[1] - from[1];
    const length = Math.hypot(dx, dy);
    if (length < 1e-6) return;
    const ux = dx / length;
    const uy = dy / length;
    const head = Math.min(length * 0.4, 10 * s);
    const base = [to[0] - ux * head, to[1] - uy * head];
    const half = head * 0.55;

    ctx.beginPath();
    ctx.moveTo(from[0], from[1]);
    ctx.lineTo(base[0], base[1]);
    strokeWithHalo(ctx, colour, 2 * s, s);

    ctx.beginPath();
    ctx.moveTo(to[0], to[1]);
    ctx.lineTo(base[0] + uy * half, base[1] - ux * half);
    ctx.lineTo(base[0] - uy * half, base[1] + ux * half);
    ctx.closePath();
    ctx.strokeStyle = HALO_COLOUR;
    ctx.lineWidth = s;
    ctx.stroke();
    ctx.fillStyle = colour;
    ctx.fill();
  }

  /** A text label on a coloured background, above `anchor`, kept inside the canvas. */
  function drawLabel(ctx, text, anchor, colour, s) {
    const size = Math.round(13 * s);
    const pad = 3 * s;
    ctx.font = `600 ${size}px ${LABEL_FONT}`;
    ctx.textBaseline = 'top';
    const boxW = ctx.measureText(text).width + 2 * pad;
    const boxH = size + 2 * pad;
    const x = clamp(anchor[0], 0, Math.max(0, el.overlay.width - boxW));
    const y = clamp(anchor[1] - boxH - 2 * s, 0, Math.max(0, el.overlay.height - boxH));
    ctx.fillStyle = colour;
    ctx.fillRect(x, y, boxW, boxH);
    ctx.fillStyle = '#ffffff';
    ctx.fillText(text, x + pad, y + pad);
  }

  /** One pose: rotated outline, u axis (+column) and v axis (+row) arrows, and a label. */
  function drawPose(ctx, pose, highlighted, s) {
    const size = state.match.sizes.get(pose.templateId);
    const t = pose.transform;
    const label = `${pose.templateId || '?'} ${pose.score.toFixed(3)}`;
    ctx.save();
    ctx.lineJoin = 'round';
    ctx.lineCap = 'round';
    ctx.setLineDash([]);

    if (size && size.width > 0 && size.height > 0) {
      const w = size.width;
      const h = size.height;
      const corners = [[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]]
        .map(([col, row]) => toCanvas(t, col, row));
      ctx.beginPath();
      corners.forEach(([x, y], i) => (i === 0 ? ctx.moveTo(x, y) : ctx.lineTo(x, y)));
      ctx.closePath();
      if (highlighted) {
        ctx.globalAlpha = 0.25;
        ctx.fillStyle = pose.colour;
        ctx.fill();
        ctx.globalAlpha = 1;
      }
      strokeWithHalo(ctx, pose.colour, (highlighted ? 4 : 2) * s, s);

      const cc = (w - 1) / 2;
      const cr = (h - 1) / 2;
      const centre = toCanvas(t, cc, cr);
      drawArrow(ctx, centre, toCanvas(t, cc + w / 2, cr), U_AXIS_COLOUR, s);
      drawArrow(ctx, centre, toCanvas(t, cc, cr + h / 2), V_AXIS_COLOUR, s);

      const top = corners.reduce((best, c) => (c[1] < best[1] ? c : best));
      drawLabel(ctx, label, top, pose.colour, s);
    } else {
      // Template size unknown (deleted meanwhile?): a cross at the pose position.
      const x = pose.x + 0.5;
      const y = pose.y + 0.5;
      const r = 8 * s;
      ctx.beginPath();
      ctx.moveTo(x - r, y);
      ctx.lineTo(x + r, y);
      ctx.moveTo(x, y - r);
      ctx.lineTo(x, y + r);
      strokeWithHalo(ctx, pose.colour, 2 * s, s);
      drawLabel(ctx, label, [x, y - r], pose.colour, s);
    }
    ctx.restore();
  }

  /** The selection: a dashed box over a dark outline, with its size. */
  function drawSelection(ctx, sel, s) {
    if (sel.w <= 0 || sel.h <= 0) return;
    ctx.save();
    ctx.setLineDash([]);
    ctx.strokeStyle = HALO_COLOUR;
    ctx.lineWidth = 3 * s;
    ctx.strokeRect(sel.x, sel.y, sel.w, sel.h);
    ctx.setLineDash([6 * s, 4 * s]);
    ctx.strokeStyle = SELECTION_COLOUR;
    ctx.lineWidth = 1.5 * s;
    ctx.strokeRect(sel.x, sel.y, sel.w, sel.h);
    ctx.restore();
    const small = sel.w < MIN_TEMPLATE_SIDE || sel.h < MIN_TEMPLATE_SIDE;
    drawLabel(ctx, `${sel.w}x${sel.h}`, [sel.x, sel.y], small ? '#b42318' : '#3d4b5c', s);
  }

  // ---------------------------------------------------------------------------------------
  // Registering templates
  // ---------------------------------------------------------------------------------------

  /** "a=1, b = 2" -> {a: "1", b: "2"}; throws an InputError naming the bad item. */
  function parseLabels(text) {
    const labels = {};
    for (const part of text.split(',')) {
      const item = part.trim();
      if (!item) continue;
      const eq = item.indexOf('=');
      const key = eq > 0 ? item.slice(0, eq).trim() : '';
      if (!key) {
        throw new InputError(`Labels: "${item}" is not of the form key=value.`, el.templateLabels);
      }
      labels[key] = item.slice(eq + 1).trim();
    }
    return labels;
  }

  /** The ID/labels/replace part of a registration request, from the form. */
  function registrationFields() {
    const fields = {};
    const id = el.templateId.value.trim();
    if (id) fields.templateId = id;
    const labels = parseLabels(el.templateLabels.value);
    if (Object.keys(labels).length) fields.labels = labels;
    if (el.replace.checked) fields.replace = true;
    return fields;
  }

  /** The box cut out of the frame at natural resolution, as a PNG blob. */
  function cutSelection(sel) {
    const canvas = document.createElement('canvas');
    canvas.width = sel.w;
    canvas.height = sel.h;
    canvas.getContext('2d').drawImage(el.frameCanvas, sel.x, sel.y, sel.w, sel.h, 0, 0, sel.w, sel.h);
    return new Promise((resolve, reject) => {
      canvas.toBlob((blob) => (blob ? resolve(blob) : reject(new Error('the browser could not encode the box as PNG'))), 'image/png');
    });
  }

  /** POST /v1/templates with `bytes` as the image; reports, refreshes the list, checks the new ID. */
  async function registerTemplate(bytes, fields) {
    const body = Object.assign({}, fields, { image: { encoded: bytesToBase64(bytes) } });
    const info = await api('POST', '/v1/templates', body);
    const id = info.templateId || fields.templateId || '';
    rememberTemplate(Object.assign({ templateId: id }, info));
    if (id) state.checked.add(id);
    setStatus(`Registered ${id} (${num(info.width)}x${num(info.height)})`);
    await refreshTemplates();
  }

  async function registerSelection() {
    try {
      if (!state.frame) throw new InputError('Load a camera frame first, then drag a box around the part.', el.frameFile);
      const sel = state.selection;
      if (!sel || sel.w === 0 || sel.h === 0) {
        throw new InputError('Drag a box around the part on the frame first (or type Box x, y, width and height).', el.selX);
      }
      if (sel.w < MIN_TEMPLATE_SIDE || sel.h < MIN_TEMPLATE_SIDE) {
        throw new InputError(
          `The box is ${sel.w}x${sel.h} px; a template needs at least ${MIN_TEMPLATE_SIDE} px per side.`,
          sel.w < MIN_TEMPLATE_SIDE ? el.selW : el.selH,
        );
      }
      const fields = registrationFields();
      await withBusyButtons([el.registerSelection, el.registerFile], async () => {
        setStatus(`Registering the ${sel.w}x${sel.h} box…`);
        const png = await cutSelection(sel);
        await registerTemplate(await png.arrayBuffer(), fields);
      });
    } catch (err) {
      reportError('Registering failed', err);
    }
  }

  async function registerFile() {
    try {
      const file = el.templateFile.files && el.templateFile.files[0];
      if (!file) throw new InputError('Choose a template image file first.', el.templateFile);
      const fields = registrationFields();
      await withBusyButtons([el.registerSelection, el.registerFile], async () => {
        setStatus(`Registering ${file.name}…`);
        await registerTemplate(await file.arrayBuffer(), fields);
      });
    } catch (err) {
      reportError('Registering failed', err);
    }
  }

  // ---------------------------------------------------------------------------------------
  // Template list
  // ---------------------------------------------------------------------------------------

  /**
   * Reloads the list (all pages). Successes are reported in #templates-info only, so that a
   * background refresh never hides the message of what the user just did; failures go to
   * the status area.
   */
  async function refreshTemplates() {
    const generation = ++state.listGeneration;
    el.templatesInfo.textContent = 'Loading…';
    const infos = [];
    try {
      let pageToken = '';
      const seen = new Set();
      for (;;) {
        const query = new URLSearchParams({ pageSize: String(PAGE_SIZE) });
        if (pageToken) query.set('pageToken', pageToken);
        const page = await api('GET', `/v1/templates?${query}`);
        if (generation !== state.listGeneration) return; // a newer refresh took over
        if (Array.isArray(page.templates)) infos.push(...page.templates);
        pageToken = page.nextPageToken || '';
        if (!pageToken || seen.has(pageToken)) break;
        seen.add(pageToken);
      }
    } catch (err) {
      if (generation !== state.listGeneration) return;
      el.templatesInfo.textContent = 'The list could not be loaded.';
      reportError('Loading the template list failed', err);
      return;
    }

    state.templates = new Map();
    infos.forEach(rememberTemplate);
    for (const id of Array.from(state.checked)) {
      if (!state.templates.has(id)) state.checked.delete(id);
    }
    renderTemplateList(infos, generation);
  }

  function templateMeta(info) {
    const parts = [`${num(info.width)}x${num(info.height)}`];
    const labels = Object.entries(info.labels || {}).map(([k, v]) => `${k}=${v}`);
    if (labels.length) parts.push(labels.join(', '));
    return parts.join(' · ');
  }

  /** One <li>: thumbnail, checkbox with its label, Delete button. */
  function templateItem(info) {
    const id = info.templateId;
    const li = document.createElement('li');
    li.dataset.templateId = id;
    li.classList.toggle('is-checked', state.checked.has(id));
    const updated = num(info.updatedUnixMs || info.createdUnixMs);
    if (updated) li.title = `Version ${num(info.version) || 1}, updated ${new Date(updated).toLocaleString()}`;

    const img = document.createElement('img');
    img.className = 'thumb';
    img.alt = `Template ${id}`;
    img.decoding = 'async';

    const label = document.createElement('label');
    label.className = 'template-choice';
    const box = document.createElement('input');
    box.type = 'checkbox';
    box.name = 'template';
    box.value = id;
    box.checked = state.checked.has(id);
    const text = document.createElement('span');
    text.className = 'template-text';
    const name = document.createElement('span');
    name.className = 'template-name';
    name.textContent = id;
    const meta = document.createElement('span');
    meta.className = 'template-meta';
    meta.textContent = templateMeta(info);
    text.append(name, meta);
    label.append(box, text);

    const del = document.createElement('button');
    del.type = 'button';
    del.className = 'delete';
    del.textContent = 'Delete';
    del.setAttribute('aria-label', `Delete template ${id}`);

    li.append(img, label, del);
    return { li, img };
  }

  /** Replaces the list items, keeping the keyboard focus on the same template if it had it. */
  function renderTemplateList(infos, generation) {
    const active = document.activeElement;
    const focusedItem = active && el.templates.contains(active) ? active.closest('li') : null;
    const focusedId = focusedItem ? focusedItem.dataset.templateId : null;
    const focusedDelete = !!(active && active.classList && active.classList.contains('delete'));

    el.templates.textContent = '';
    const items = [];
    for (const info of infos) {
      const item = templateItem(info);
      items.push({ info, img: item.img });
      el.templates.append(item.li);
    }
    el.templatesInfo.textContent = infos.length
      ? `${plural(infos.length, 'template')} on the server; check the ones to look for.`
      : 'No templates registered yet.';

    if (focusedItem) {
      const li = Array.from(el.templates.children).find((item) => item.dataset.templateId === focusedId);
      const target = li ? li.querySelector(focusedDelete ? 'button.delete' : 'input[name="template"]') : el.refreshTemplates;
      if (target) target.focus();
    }
    loadThumbnails(items, generation);
  }

  function thumbnailKey(info) {
    return `${info.templateId}\n${info.contentSha256 || ''}\n${info.version || ''}`;
  }

  /** Fills the thumbnails, a few requests at a time; cached per template content. */
  async function loadThumbnails(items, generation) {
    const queue = items.slice();
    const worker = async () => {
      while (queue.length && generation === state.listGeneration) {
        const { info, img } = queue.shift();
        await loadThumbnail(info, img);
      }
    };
    await Promise.all(Array.from({ length: THUMBNAIL_CONCURRENCY }, worker));
  }

  async function loadThumbnail(info, img) {
    const key = thumbnailKey(info);
    let url = state.thumbnails.get(key);
    if (!url) {
      try {
        const full = await api('GET', `${templatePath(info.templateId)}?includeImage=true`);
        const encoded = full.image && full.image.encoded;
        if (!encoded) throw new Error('no image in the answer');
        url = `data:image/png;base64,${encoded}`;
        state.thumbnails.set(key, url);
      } catch (err) {
        img.classList.add('missing');
        img.title = `No thumbnail: ${(err && err.message) || err}`;
        return;
      }
    }
    img.src = url;
  }

  function checkedTemplateIds() {
    return Array.from(el.templates.querySelectorAll('input[name="template"]:checked'), (box) => box.value);
  }

  async function deleteTemplate(id, button) {
    if (!window.confirm(`Delete template "${id}"? Matches can no longer use it.`)) return;
    // Keyboard users keep their place: focus moves to the next template's checkbox (or the
    // previous one's, or the refresh button) instead of falling back to the top of the page.
    const item = button.closest('li');
    const neighbour = item && (item.nextElementSibling || item.previousElementSibling);
    const neighbourId = neighbour ? neighbour.dataset.templateId : null;
    button.setAttribute('aria-disabled', 'true');
    button.disabled = true;
    try {
      const result = await api('DELETE', templatePath(id));
      state.checked.delete(id);
      for (const key of Array.from(state.thumbnails.keys())) {
        if (key.startsWith(`${id}\n`)) state.thumbnails.delete(key);
      }
      setStatus(result.deleted ? `Deleted ${id}` : `${id} was not found: nothing was deleted`);
      await refreshTemplates();
      const next = Array.from(el.templates.children).find((li) => li.dataset.templateId === neighbourId);
      const target = next ? next.querySelector('input[name="template"]') : el.refreshTemplates;
      if (target) target.focus();
    } catch (err) {
      button.disabled = false;
      button.removeAttribute('aria-disabled');
      button.focus();
      reportError(`Deleting ${id} failed`, err);
    }
  }

  function initTemplateList() {
    el.refreshTemplates.addEventListener('click', () => refreshTemplates());
    el.templates.addEventListener('change', (event) => {
      const box = event.target;
      if (!(box instanceof HTMLInputElement) || box.name !== 'template') return;
      if (box.checked) state.checked.add(box.value);
      else state.checked.delete(box.value);
      const li = box.closest('li');
      if (li) li.classList.toggle('is-checked', box.checked);
    });
    el.templates.addEventListener('click', (event) => {
      const button = event.target instanceof Element ? event.target.closest('button.delete') : null;
      if (!button) return;
      const li = button.closest('li');
      if (li) deleteTemplate(li.dataset.templateId, button);
    });
  }

  // ---------------------------------------------------------------------------------------
  // Search options
  // ---------------------------------------------------------------------------------------

  /**
   * The number in `input`, undefined when it is empty; throws an InputError naming the field
   * when it is not a number or fails `valid` (`rule` says what is expected).
   */
  function readNumber(input, valid, rule) {
    if (input.validity && input.validity.badInput) {
      throw new InputError(`${fieldName(input)} is not a number.`, input);
    }
    const text = input.value.trim();
    if (text === '') return undefined;
    const value = Number(text);
    if (!Number.isFinite(value) || !valid(value)) {
      throw new InputError(`${fieldName(input)} must be ${rule} (it is ${text}).`, input);
    }
    return value;
  }

  /** MatchOptions from the form; only the fields that are filled in. */
  function buildOptions() {
    const options = {};
    const set = (key, value) => {
      if (value !== undefined) options[key] = value;
    };
    set('maxInstances', readNumber(el.maxInstances,
      (v) => Number.isInteger(v) && v >= 1 && v <= 1000, 'a whole number from 1 to 1000'));
    set('minScore', readNumber(el.minScore, (v) => v > 0 && v < 1, 'greater than 0 and less than 1'));
    set('angleStartDeg', readNumber(el.angleStart, (v) => v >= -360 && v <= 360, 'from -360 to 360'));
    set('angleExtentDeg', readNumber(el.angleExtent, (v) => v > 0 && v <= 360, 'greater than 0 and at most 360'));
    const scaleMin = readNumber(el.scaleMin, (v) => v >= 0, 'a number of at least 0');
    const scaleMax = readNumber(el.scaleMax, (v) => v >= 0, 'a number of at least 0');
    if (scaleMin > 0 && scaleMax > 0 && scaleMin > scaleMax) {
      throw new InputError(`${fieldName(el.scaleMax)} (${scaleMax}) must not be smaller than ${fieldName(el.scaleMin)} (${scaleMin}).`, el.scaleMax);
    }
    set('scaleMin', scaleMin);
    set('scaleMax', scaleMax);
    if (el.polarity.value) options.polarity = el.polarity.value;
    if (el.method.value) options.method = el.method.value;
    set('timeoutMs', readNumber(el.timeoutMs,
      (v) => Number.isInteger(v) && v >= 1 && v <= 600000, 'a whole number from 1 to 600000'));
    if (el.noRefine.checked) options.noRefine = true;
    if (el.suppressAcross.checked) options.suppressAcrossTemplates = true;
    return options;
  }

  // ---------------------------------------------------------------------------------------
  // Matching and results
  // ---------------------------------------------------------------------------------------

  /** Forgets the last match: overlay poses, table, timings. */
  function clearMatch() {
    state.match = null;
    state.highlighted = -1;
    el.overlay.removeAttribute('data-drawn-poses');
    el.posesBody.textContent = '';
    el.posesCaption.textContent = 'Poses found by the last match';
    el.timings.textContent = '';
  }

  /**
   * The pose's 2x3 transform (template column/row to image x/y); the server always sends it.
   * An answer without a valid one gets the translation to (x, y) with the angle and scales,
   * about the template's top-left pixel, so the table still lists it.
   */
  function poseTransform(raw) {
    const t = Array.isArray(raw.transform) ? raw.transform.map(Number) : [];
    if (t.length === 6 && t.every(Number.isFinite)) return t;
    const a = (num(raw.angleDeg) * Math.PI) / 180;
    const sx = num(raw.scaleX) || 1;
    const sy = num(raw.scaleY) || 1;
    return [sx * Math.cos(a), sy * Math.sin(a), num(raw.x), -sx * Math.sin(a), sy * Math.cos(a), num(raw.y)];
  }

  /** A pose with every field present (absent = 0 in proto3 JSON). */
  function normalisePose(raw, index, fallbackId) {
    return {
      index,
      templateId: raw.templateId || fallbackId,
      x: num(raw.x),
      y: num(raw.y),
      angleDeg: num(raw.angleDeg),
      scaleX: num(raw.scaleX),
      scaleY: num(raw.scaleY),
      score: num(raw.score),
      networkScore: num(raw.networkScore),
      transform: poseTransform(raw),
      colour: '',
    };
  }

  /** Fetches the infos (sizes) of templates the list does not know yet; failures are ignored. */
  async function ensureTemplateInfos(ids) {
    const missing = ids.filter((id) => id && !state.templates.has(id));
    await Promise.all(missing.map(async (id) => {
      try {
        rememberTemplate(await api('GET', templatePath(id)));
      } catch (_) {
        // Drawn as a cross without the outline.
      }
    }));
  }

  function cell(text, className) {
    const td = document.createElement('td');
    td.textContent = text;
    if (className) td.className = className;
    return td;
  }

  function renderPoseTable(poses) {
    el.posesBody.textContent = '';
    for (const pose of poses) {
      const tr = document.createElement('tr');
      tr.dataset.poseIndex = String(pose.index);
      const templateCell = document.createElement('td');
      templateCell.className = 'template-cell';
      const swatch = document.createElement('span');
      swatch.className = 'swatch';
      swatch.style.backgroundColor = pose.colour; // CSSOM, allowed by the CSP
      templateCell.append(swatch, document.createTextNode(pose.templateId));
      tr.append(
        cell(String(pose.index + 1)),
        templateCell,
        cell(pose.x.toFixed(2)),
        cell(pose.y.toFixed(2)),
        cell(pose.angleDeg.toFixed(2)),
        cell(pose.scaleX.toFixed(2)),
        cell(pose.scaleY.toFixed(2)),
        cell(pose.score.toFixed(3)),
      );
      el.posesBody.append(tr);
    }
    el.posesCaption.textContent = poses.length
      ? `Poses found by the last match: ${poses.length}`
      : 'Poses found by the last match: none';
  }

  function renderTimings(response, count) {
    const t = response.timings || {};
    const ms = (v) => num(v).toFixed(1);
    let text = `${count} ${count === 1 ? 'pose' : 'poses'} in ${ms(t.totalMs)} ms (decode ${ms(t.decodeMs)}, queue ${ms(t.queueMs)}, ` +
      `network ${ms(t.networkMs)}, post-processing ${ms(t.postprocessMs)})`;
    if (response.timedOut) text += ' — timed out';
    el.timings.textContent = text;
  }

  /** Shows a MatchResponse: overlay, table, timings, status. */
  function showMatch(response, ids, frame) {
    const fallbackId = response.templateId || (ids.length === 1 ? ids[0] : '');
    const poses = (Array.isArray(response.poses) ? response.poses : [])
      .map((raw, i) => normalisePose(raw, i, fallbackId));

    // One colour per template: the checked order first, then any other ID in the answer.
    const colours = new Map(ids.map((id, i) => [id, templateColour(i)]));
    for (const pose of poses) {
      if (!colours.has(pose.templateId)) colours.set(pose.templateId, templateColour(colours.size));
      pose.colour = colours.get(pose.templateId);
    }
    // Sizes are kept with the match, so a later list refresh or delete does not change it.
    const sizes = new Map();
    for (const id of colours.keys()) {
      const info = state.templates.get(id);
      if (info) sizes.set(id, { width: num(info.width), height: num(info.height) });
    }

    state.match = { poses, sizes };
    state.highlighted = -1;
    redraw();
    el.overlay.dataset.drawnPoses = String(poses.length);
    renderPoseTable(poses);
    renderTimings(response, poses.length);

    let message = poses.length
      ? `Found ${plural(poses.length, 'pose')} of ${ids.join(', ')}.`
      : `No pose of ${ids.join(', ')} found.`;
    if (response.timedOut) message += ' The search timed out: the list may be incomplete.';
    const w = num(response.imageWidth);
    const h = num(response.imageHeight);
    if (w && h && (w !== frame.width || h !== frame.height)) {
      message += ` Note: the server read the frame as ${w}x${h}, the browser as ${frame.width}x${frame.height}.`;
    }
    setStatus(message);
  }

  async function runMatch() {
    const ids = checkedTemplateIds();
    const missing = [];
    if (!state.frame) missing.push('load a camera frame');
    if (!ids.length) missing.push('check at least one template in the list');
    if (missing.length) {
      setStatus(`To find templates, first ${missing.join(' and ')}.`, true);
      return;
    }
    if (ids.length > MAX_TEMPLATES_PER_MATCH) {
      setStatus(`At most ${MAX_TEMPLATES_PER_MATCH} templates can be searched at once; ${ids.length} are checked.`, true);
      return;
    }
    let options;
    try {
      options = buildOptions();
    } catch (err) {
      reportError('', err);
      return;
    }

    const frame = state.frame;
    await withBusyButtons([el.runMatch], async () => {
      try {
        setStatus(`Looking for ${ids.join(', ')} in ${frame.name}…`);
        await nextPaint(); // show the message before the (possibly long) encoding below
        if (frame.base64 === null) frame.base64 = bytesToBase64(frame.bytes);
        const body = { templateIds: ids, image: { encoded: frame.base64 } };
        if (Object.keys(options).length) body.options = options;
        const response = await api('POST', '/v1/match', body);
        if (state.frame !== frame) return; // another frame was loaded meanwhile
        const poseIds = (response.poses || []).map((p) => p.templateId).filter(Boolean);
        await ensureTemplateInfos(Array.from(new Set(ids.concat(poseIds))));
        if (state.frame !== frame) return;
        showMatch(response, ids, frame);
      } catch (err) {
        reportError('Matching failed', err);
      }
    });
  }

  function initResults() {
    el.runMatch.addEventListener('click', runMatch);
    // Hovering a row highlights its pose on the frame.
    el.posesBody.addEventListener('mouseover', (event) => {
      const tr = event.target instanceof Element ? event.target.closest('tr') : null;
      const index = tr ? Number(tr.dataset.poseIndex) : -1;
      if (index !== state.highlighted) {
        el.posesBody.querySelectorAll('tr.is-highlighted').forEach((row) => row.classList.remove('is-highlighted'));
        if (tr) tr.classList.add('is-highlighted');
        state.highlighted = index;
        redraw();
      }
    });
    el.posesBody.addEventListener('mouseleave', () => {
      el.posesBody.querySelectorAll('tr.is-highlighted').forEach((row) => row.classList.remove('is-highlighted'));
      if (state.highlighted !== -1) {
        state.highlighted = -1;
        redraw();
      }
    });
  }

  // ---------------------------------------------------------------------------------------
  // Start
  // ---------------------------------------------------------------------------------------

  function init() {
    setStatus('Ready: load a camera frame to begin.');
    initToken();
    initDropZone();
    initSelection();
    initTemplateList();
    initResults();

    el.frameFile.addEventListener('change', () => loadFrame(el.frameFile.files && el.frameFile.files[0]));
    el.registerSelection.addEventListener('click', registerSelection);
    el.registerFile.addEventListener('click', registerFile);
    // A field marked invalid is unmarked as soon as it is edited.
    document.addEventListener('input', (event) => {
      if (event.target instanceof Element) event.target.removeAttribute('aria-invalid');
    });
    document.addEventListener('change', (event) => {
      if (event.target instanceof Element) event.target.removeAttribute('aria-invalid');
    });

    refreshTemplates();
  }

  init();
}());

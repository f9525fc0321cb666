// The report page's 3D view: a small WebGL2 renderer of the run's Gaussians (coin_cl/report_html.py
// embeds them in the page as base64). Each Gaussian is drawn as a screen-space ellipse: its 3D
// covariance (precomputed in Python) is projected with the camera's Jacobian (EWA splatting, as 3DGS),
// shaded exp(-r^2/2) x opacity and alpha-blended back to front after a depth sort on the CPU (a
// 16-bit counting sort whenever the camera moves). Colours are the degree-0 SH (view-independent).
// Cameras follow the engine's convention: OpenCV axes (x right, y down, z forward), K in pixels.
// Orbit controls: drag to orbit about the focus point, shift/right-drag to pan, wheel to zoom.
// The page's test reads the status element: "drew N non-blank pixels" after the first frame.
"use strict";
(function () {
  const status = document.getElementById("viewer-status");
  const canvas = document.getElementById("viewer");
  const data = JSON.parse(document.getElementById("splat-data").textContent);
  const BG = [0.13, 0.13, 0.15];

  function report(msg, nonblank) {
    status.textContent = msg;
    if (nonblank !== undefined) status.dataset.nonblank = String(nonblank);
  }
  function b64(s) {
    const bin = atob(s);
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out.buffer;
  }

  const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true });
  if (!gl) {
    report("WebGL2 is not available in this browser: the 3D view cannot draw (the orbit GIF shows the result)", 0);
    return;
  }
  const n = data.n;
  if (n === 0) {
    report("no Gaussians to draw", 0);
    return;
  }
  const geo = new Float32Array(b64(data.geometry)); // n x 9: x y z, c00 c01 c02 c11 c12 c22
  const rgba = new Uint8Array(b64(data.colors)); // n x 4

  const vs = `#version 300 es
  precision highp float; precision highp int; precision highp usampler2D;
  uniform highp sampler2D u_pos, u_covA, u_covB; uniform sampler2D u_col;
  uniform mat4 u_view; uniform vec4 u_K; uniform vec2 u_size;
  in vec2 a_corner; in uint a_index;
  out vec4 v_col; out vec2 v_pos;
  ivec2 at(uint i) { return ivec2(int(i & 2047u), int(i >> 11)); }
  void main() {
    ivec2 t = at(a_index);
    vec3 p = texelFetch(u_pos, t, 0).xyz;
    vec4 ca = texelFetch(u_covA, t, 0); vec2 cb = texelFetch(u_covB, t, 0).xy;
    vec4 c = u_view * vec4(p, 1.0);
    if (c.z < 0.01) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
    mat3 S = mat3(ca.x, ca.y, ca.z, ca.y, ca.w, cb.x, ca.z, cb.x, cb.y);
    mat3 R = mat3(u_view);
    float z2 = c.z * c.z;
    mat3 J = mat3(u_K.x / c.z, 0.0, 0.0, 0.0, u_K.y / c.z, 0.0,
                  -u_K.x * c.x / z2, -u_K.y * c.y / z2, 0.0);
    mat3 M = J * R;
    mat3 C = M * S * transpose(M);
    float a = C[0][0] + 0.3, b = C[0][1], d = C[1][1] + 0.3;  // + a pixel's low-pass, as 3DGS
    float mid = 0.5 * (a + d), rad = length(vec2(0.5 * (a - d), b));
    float l1 = mid + rad, l2 = mid - rad;
    if (l2 <= 0.0) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
    vec2 dir = abs(b) < 1e-9 ? (a >= d ? vec2(1.0, 0.0) : vec2(0.0, 1.0)) : normalize(vec2(b, l1 - a));
    vec2 major = min(sqrt(2.0 * l1), 1024.0) * dir;
    vec2 minor = min(sqrt(2.0 * l2), 1024.0) * vec2(dir.y, -dir.x);
    vec2 px = vec2(u_K.x * c.x / c.z + u_K.z, u_K.y * c.y / c.z + u_K.w);
    vec2 q = px + a_corner.x * major + a_corner.y * minor;
    gl_Position = vec4(2.0 * q.x / u_size.x - 1.0, 1.0 - 2.0 * q.y / u_size.y, 0.0, 1.0);
    v_col = texelFetch(u_col, t, 0);
    v_pos = a_corner;
  }`;
  const fs = `#version 300 es
  precision highp float;
  in vec4 v_col; in vec2 v_pos; out vec4 color;
  void main() {
    float r2 = dot(v_pos, v_pos);
    if (r2 > 4.0) discard;
    float alpha = min(0.99, exp(-r2) * v_col.a);
    color = vec4(v_col.rgb * alpha, alpha);
  }`;

  function shader(type, src) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error("shader: " + gl.getShaderInfoLog(s));
    return s;
  }
  const prog = gl.createProgram();
  gl.attachShader(prog, shader(gl.VERTEX_SHADER, vs));
  gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error("link: " + gl.getProgramInfoLog(prog));
  gl.useProgram(prog);

  // The Gaussians live in textures 2048 wide (texelFetch by index), so that a sort re-uploads only
  // the n indices.
  const TW = 2048, TH = Math.ceil(n / TW);
  function texture(unit, name, internal, format, type, arr) {
    const t = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, TW, TH, 0, format, type, arr);
    gl.uniform1i(gl.getUniformLocation(prog, name), unit);
  }
  const pos = new Float32Array(TW * TH * 4), covA = new Float32Array(TW * TH * 4);
  const covB = new Float32Array(TW * TH * 4), col = new Uint8Array(TW * TH * 4);
  for (let i = 0; i < n; i++) {
    const g = 9 * i;
    pos.set([geo[g], geo[g + 1], geo[g + 2], 1], 4 * i);
    covA.set([geo[g + 3], geo[g + 4], geo[g + 5], geo[g + 6]], 4 * i);
    covB.set([geo[g + 7], geo[g + 8], 0, 0], 4 * i);
  }
  col.set(rgba);
  texture(0, "u_pos", gl.RGBA32F, gl.RGBA, gl.FLOAT, pos);
  texture(1, "u_covA", gl.RGBA32F, gl.RGBA, gl.FLOAT, covA);
  texture(2, "u_covB", gl.RGBA32F, gl.RGBA, gl.FLOAT, covB);
  texture(3, "u_col", gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, col);

  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  const corners = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, corners);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-2, -2, 2, -2, 2, 2, -2, 2]), gl.STATIC_DRAW);
  const aCorner = gl.getAttribLocation(prog, "a_corner");
  gl.enableVertexAttribArray(aCorner);
  gl.vertexAttribPointer(aCorner, 2, gl.FLOAT, false, 0, 0);
  const indexBuf = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, indexBuf);
  const aIndex = gl.getAttribLocation(prog, "a_index");
  gl.enableVertexAttribArray(aIndex);
  gl.vertexAttribIPointer(aIndex, 1, gl.UNSIGNED_INT, 0, 0);
  gl.vertexAttribDivisor(aIndex, 1);

  gl.disable(gl.DEPTH_TEST);
  gl.enable(gl.BLEND);
  gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA); // premultiplied, back to front

  // Camera: eye and camera-to-world rotation columns (right, down, forward), OpenCV axes.
  const cams = data.cameras;
  let cam, target, K;
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  function rotate(v, axis, ang) { // Rodrigues
    const c = Math.cos(ang), s = Math.sin(ang), k = axis;
    const cr = [k[1] * v[2] - k[2] * v[1], k[2] * v[0] - k[0] * v[2], k[0] * v[1] - k[1] * v[0]];
    return add(add(mul(v, c), mul(cr, s)), mul(k, dot(k, v) * (1 - c)));
  }
  function useCamera(i) {
    const c = cams[i], V = c.viewmat; // world-to-camera rows
    const right = V[0].slice(0, 3), down = V[1].slice(0, 3), fwd = V[2].slice(0, 3);
    const t = [V[0][3], V[1][3], V[2][3]];
    const eye = mul(add(add(mul(right, t[0]), mul(down, t[1])), mul(fwd, t[2])), -1);
    cam = { eye: eye, right: right, down: down, fwd: fwd };
    target = add(eye, mul(fwd, c.focus));
    K = c.K;
    sortAndDraw();
  }
  const up = data.up;
  // Dragging right or down turns the scene with the pointer (the camera goes left or up), as in
  // most 3D viewers; 0.3 degrees a pixel.
  function orbit(dx, dy) {
    const ang = -dx * 0.005, pitch = -dy * 0.005;
    for (const [axis, a] of [[up, ang], [cam.right, pitch]]) {
      cam.eye = add(target, rotate(sub(cam.eye, target), axis, a));
      cam.right = rotate(cam.right, axis, a);
      cam.down = rotate(cam.down, axis, a);
      cam.fwd = rotate(cam.fwd, axis, a);
    }
  }
  function viewMatrix() { // column-major for WebGL
    const r = cam.right, d = cam.down, f = cam.fwd, e = cam.eye;
    return new Float32Array([r[0], d[0], f[0], 0, r[1], d[1], f[1], 0, r[2], d[2], f[2], 0,
      -dot(r, e), -dot(d, e), -dot(f, e), 1]);
  }

  const order = new Uint32Array(n), depthKey = new Uint32Array(n), counts = new Uint32Array(65536);
  function sort() { // far to near, 16-bit counting sort on camera z
    let lo = Infinity, hi = -Infinity;
    const zs = new Float32Array(n);
    for (let i = 0; i < n; i++) {
      const g = 9 * i;
      const z = (geo[g] - cam.eye[0]) * cam.fwd[0] + (geo[g + 1] - cam.eye[1]) * cam.fwd[1] +
        (geo[g + 2] - cam.eye[2]) * cam.fwd[2];
      zs[i] = z;
      if (z < lo) lo = z;
      if (z > hi) hi = z;
    }
    const scale = 65535 / Math.max(hi - lo, 1e-9);
    counts.fill(0);
    for (let i = 0; i < n; i++) {
      depthKey[i] = 65535 - Math.floor((zs[i] - lo) * scale);
      counts[depthKey[i]]++;
    }
    for (let i = 1; i < 65536; i++) counts[i] += counts[i - 1];
    for (let i = n - 1; i >= 0; i--) order[--counts[depthKey[i]]] = i;
    gl.bindBuffer(gl.ARRAY_BUFFER, indexBuf);
    gl.bufferData(gl.ARRAY_BUFFER, order, gl.DYNAMIC_DRAW);
  }
  function draw() {
    const w = canvas.width, h = canvas.height, c = cams[current];
    // the captured camera's focal length, scaled to the canvas (width fitted)
    const s = w / c.width;
    gl.viewport(0, 0, w, h);
    gl.clearColor(BG[0], BG[1], BG[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "u_view"), false, viewMatrix());
    gl.uniform4f(gl.getUniformLocation(prog, "u_K"), K[0][0] * s, K[1][1] * s, K[0][2] * s,
      K[1][2] * s + 0.5 * (h - c.height * s));
    gl.uniform2f(gl.getUniformLocation(prog, "u_size"), w, h);
    gl.drawArraysInstanced(gl.TRIANGLE_FAN, 0, 4, n);
  }
  let pending = false;
  function sortAndDraw() {
    sort();
    draw();
  }
  function later() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; sortAndDraw(); });
  }

  // How much the first frame drew: pixels that differ from the background (the page's test reads it).
  function nonBlank() {
    const w = canvas.width, h = canvas.height, px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    const bg = BG.map((v) => Math.round(v * 255));
    let count = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - bg[0]) + Math.abs(px[i + 1] - bg[1]) + Math.abs(px[i + 2] - bg[2]) > 6) count++;
    }
    return count;
  }

  const pick = document.getElementById("viewer-camera");
  let current = data.start;
  cams.forEach((c, i) => {
    const o = document.createElement("option");
    o.value = String(i);
    o.textContent = c.label;
    pick.appendChild(o);
  });
  pick.value = String(current);
  pick.addEventListener("change", () => { current = Number(pick.value); useCamera(current); });
  document.getElementById("viewer-reset").addEventListener("click", () => useCamera(current));

  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX;
    drag.y = e.clientY;
    if (drag.pan) {
      const dist = Math.hypot(...sub(cam.eye, target)), k = dist / (K[0][0] * canvas.width / cams[current].width);
      const shift = add(mul(cam.right, -dx * k), mul(cam.down, -dy * k));
      cam.eye = add(cam.eye, shift);
      target = add(target, shift);
    } else {
      orbit(dx, dy);
    }
    later();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const f = Math.exp(Math.sign(e.deltaY) * 0.1);
    cam.eye = add(target, mul(sub(cam.eye, target), f));
    later();
  }, { passive: false });

  useCamera(current);
  const drawn = nonBlank();
  report("drew " + drawn + " non-blank pixels of " + canvas.width * canvas.height +
    " (" + n + " Gaussians)", drawn);
})();

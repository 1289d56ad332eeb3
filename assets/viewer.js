// skillaug viewer: plays back the humanoid and its objects from the scene
// JSON in the page (see src/view.rs). WebGL 1, z up, metres.
"use strict";
(function () {
  const errorsEl = document.getElementById("errors");
  const state = { frame: 0, played: 0, errors: [] };
  function fail(msg) {
    state.errors.push(String(msg));
    errorsEl.textContent = state.errors.join("\n");
  }
  window.addEventListener("error", (e) => fail("error: " + e.message));

  // ---------- small vector / quaternion / matrix helpers ----------
  function qmul(a, b) {
    return [
      a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
      a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
      a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
      a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
    ];
  }
  function qrot(q, v) {
    const tx = 2 * (q[1] * v[2] - q[2] * v[1]);
    const ty = 2 * (q[2] * v[0] - q[0] * v[2]);
    const tz = 2 * (q[0] * v[1] - q[1] * v[0]);
    return [
      v[0] + q[3] * tx + (q[1] * tz - q[2] * ty),
      v[1] + q[3] * ty + (q[2] * tx - q[0] * tz),
      v[2] + q[3] * tz + (q[0] * ty - q[1] * tx),
    ];
  }
  function perspective(fovy, aspect, near, far) {
    const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1,
      0, 0, 2 * far * near * nf, 0]);
  }
  function lookAt(eye, at, up) {
    let z = [eye[0] - at[0], eye[1] - at[1], eye[2] - at[2]];
    let l = Math.hypot(z[0], z[1], z[2]) || 1;
    z = z.map((v) => v / l);
    let x = [up[1] * z[2] - up[2] * z[1], up[2] * z[0] - up[0] * z[2], up[0] * z[1] - up[1] * z[0]];
    l = Math.hypot(x[0], x[1], x[2]) || 1;
    x = x.map((v) => v / l);
    const y = [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]];
    const d = (a) => a[0] * eye[0] + a[1] * eye[1] + a[2] * eye[2];
    return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
      -d(x), -d(y), -d(z), 1]);
  }
  function matmul(a, b) {
    const o = new Float32Array(16);
    for (let c = 0; c < 4; c++)
      for (let r = 0; r < 4; r++) {
        let s = 0;
        for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
        o[c * 4 + r] = s;
      }
    return o;
  }
  function f32(b64) {
    if (!b64) return new Float32Array(0);
    const bin = atob(b64);
    const buf = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) buf[i] = bin.charCodeAt(i);
    return new Float32Array(buf.buffer);
  }

  // ---------- meshes (positions + normals, local frame) ----------
  // A capsule or cylinder lies along z with half length h; a sphere is a
  // capsule with h = 0.
  function capsuleMesh(r, h, cyl) {
    const P = [], N = [], I = [];
    const seg = 16, ring = 8;
    const rows = [];
    if (cyl) {
      rows.push([0, -h, 0, -1, true], [r, -h, 0, -1, true], [r, -h, 0, 0, false],
        [r, h, 0, 0, false], [r, h, 0, 1, true], [0, h, 0, 1, true]);
    } else {
      for (let i = 0; i <= ring; i++) {
        const a = -Math.PI / 2 + (i / ring) * (Math.PI / 2);
        rows.push([r * Math.cos(a), -h + r * Math.sin(a), Math.cos(a), Math.sin(a)]);
      }
      for (let i = 0; i <= ring; i++) {
        const a = (i / ring) * (Math.PI / 2);
        rows.push([r * Math.cos(a), h + r * Math.sin(a), Math.cos(a), Math.sin(a)]);
      }
    }
    for (const row of rows) {
      for (let s = 0; s <= seg; s++) {
        const t = (s / seg) * 2 * Math.PI, c = Math.cos(t), sn = Math.sin(t);
        P.push(row[0] * c, row[0] * sn, row[1]);
        if (cyl) N.push(row[3] === 0 ? c : 0, row[3] === 0 ? sn : 0, row[3]);
        else N.push(row[2] * c, row[2] * sn, row[3]);
      }
    }
    for (let k = 0; k + 1 < rows.length; k++)
      for (let s = 0; s < seg; s++) {
        const a = k * (seg + 1) + s, b = a + seg + 1;
        I.push(a, a + 1, b, a + 1, b + 1, b);
      }
    return { P, N, I };
  }
  function boxMesh(e) {
    const P = [], N = [], I = [];
    for (let ax = 0; ax < 3; ax++)
      for (const sg of [-1, 1]) {
        const u = (ax + 1) % 3, v = (ax + 2) % 3, base = P.length / 3;
        for (const [a, b] of [[-1, -1], [1, -1], [1, 1], [-1, 1]]) {
          const p = [0, 0, 0], n = [0, 0, 0];
          p[ax] = sg * e[ax]; p[u] = a * e[u]; p[v] = b * e[v]; n[ax] = sg;
          P.push(...p); N.push(...n);
        }
        if (sg > 0) I.push(base, base + 1, base + 2, base, base + 2, base + 3);
        else I.push(base, base + 2, base + 1, base, base + 3, base + 2);
      }
    return { P, N, I };
  }
  function triMesh(verts, tris) {
    // flat shading: one vertex per triangle corner
    const P = [], N = [], I = [];
    for (let t = 0; t < tris.length; t += 3) {
      const a = tris[t] * 3, b = tris[t + 1] * 3, c = tris[t + 2] * 3;
      const u = [verts[b] - verts[a], verts[b + 1] - verts[a + 1], verts[b + 2] - verts[a + 2]];
      const v = [verts[c] - verts[a], verts[c + 1] - verts[a + 1], verts[c + 2] - verts[a + 2]];
      let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
      const l = Math.hypot(n[0], n[1], n[2]) || 1;
      n = n.map((x) => x / l);
      for (const i of [a, b, c]) {
        P.push(verts[i], verts[i + 1], verts[i + 2]);
        N.push(...n);
        I.push(I.length);
      }
    }
    return { P, N, I };
  }

  // ---------- GL setup ----------
  const canvas = document.getElementById("gl");
  const gl = canvas.getContext("webgl", { antialias: true, stencil: true, preserveDrawingBuffer: true });
  if (!gl) {
    fail("error: this browser gives no WebGL context; the viewer needs WebGL");
    return;
  }
  const uint32 = gl.getExtension("OES_element_index_uint");
  const VS = `
    attribute vec3 aPos; attribute vec3 aNor;
    uniform mat4 uVP; uniform vec3 uT; uniform vec4 uQ; uniform float uFlat;
    varying vec3 vN; varying vec3 vW;
    vec3 qrot(vec4 q, vec3 v) { vec3 t = 2.0 * cross(q.xyz, v); return v + q.w * t + cross(q.xyz, t); }
    void main() {
      vec3 p = qrot(uQ, aPos) + uT;
      if (uFlat > 0.5) p.z = 0.002;
      vN = qrot(uQ, aNor); vW = p;
      gl_Position = uVP * vec4(p, 1.0);
    }`;
  const FS = `
    #ifdef GL_FRAGMENT_PRECISION_HIGH
    precision highp float;
    #else
    precision mediump float;
    #endif
    varying vec3 vN; varying vec3 vW;
    uniform vec3 uColor; uniform float uAlpha; uniform float uGround; uniform float uShadow;
    void main() {
      if (uShadow > 0.5) { gl_FragColor = vec4(0.0, 0.0, 0.0, 0.28); return; }
      vec3 c = uColor;
      if (uGround > 0.5) {
        float k = mod(floor(vW.x) + floor(vW.y), 2.0);
        c = mix(vec3(0.62, 0.64, 0.66), vec3(0.55, 0.57, 0.59), k);
        float fade = clamp(length(vW.xy - uColor.xy) / 25.0, 0.0, 1.0);
        gl_FragColor = vec4(mix(c, vec3(0.13, 0.14, 0.16), fade), 1.0);
        return;
      }
      vec3 n = normalize(vN);
      float d = max(dot(n, normalize(vec3(0.35, 0.25, 1.0))), 0.0);
      float b = max(dot(n, normalize(vec3(-0.6, -0.4, 0.3))), 0.0);
      gl_FragColor = vec4(c * (0.30 + 0.12 * (0.5 + 0.5 * n.z) + 0.62 * d + 0.15 * b), uAlpha);
    }`;
  function shader(type, src) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  const prog = gl.createProgram();
  gl.attachShader(prog, shader(gl.VERTEX_SHADER, VS));
  gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, FS));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  gl.useProgram(prog);
  const loc = {};
  for (const n of ["uVP", "uT", "uQ", "uFlat", "uShadow", "uColor", "uAlpha", "uGround"])
    loc[n] = gl.getUniformLocation(prog, n);
  const aPos = gl.getAttribLocation(prog, "aPos"), aNor = gl.getAttribLocation(prog, "aNor");
  function upload(m) {
    const big = m.P.length / 3 > 65535;
    if (big && !uint32) return null;
    const vb = gl.createBuffer(), nb = gl.createBuffer(), ib = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, vb);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(m.P), gl.STATIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER, nb);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(m.N), gl.STATIC_DRAW);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, big ? new Uint32Array(m.I) : new Uint16Array(m.I), gl.STATIC_DRAW);
    return { vb, nb, ib, n: m.I.length, type: big ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT };
  }
  function draw(mesh, t, q, color, alpha, flat) {
    if (!mesh) return;
    gl.bindBuffer(gl.ARRAY_BUFFER, mesh.vb);
    gl.vertexAttribPointer(aPos, 3, gl.FLOAT, false, 0, 0);
    gl.enableVertexAttribArray(aPos);
    gl.bindBuffer(gl.ARRAY_BUFFER, mesh.nb);
    gl.vertexAttribPointer(aNor, 3, gl.FLOAT, false, 0, 0);
    gl.enableVertexAttribArray(aNor);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, mesh.ib);
    gl.uniform3fv(loc.uT, t);
    gl.uniform4fv(loc.uQ, q);
    gl.uniform3fv(loc.uColor, color);
    gl.uniform1f(loc.uAlpha, alpha);
    gl.uniform1f(loc.uFlat, flat ? 1 : 0);
    gl.uniform1f(loc.uShadow, flat ? 1 : 0);
    gl.drawElements(gl.TRIANGLES, mesh.n, mesh.type, 0);
  }

  // ---------- scene ----------
  const scene = JSON.parse(document.getElementById("scene").textContent);
  const geoms = scene.bodies.map((b) =>
    b.geoms.map((g) => {
      let m;
      if (g.kind === "box") m = boxMesh(g.size);
      else if (g.kind === "sphere") m = capsuleMesh(g.size[0], 0, false);
      else m = capsuleMesh(g.size[0], g.size[1], g.kind === "cylinder");
      return { mesh: upload(m), pos: g.pos, quat: g.quat };
    }));
  const objects = scene.objects.map((o) => upload(triMesh(f32(o.verts), o.tris)));
  const ground = upload({ P: [-200, -200, 0, 200, -200, 0, 200, 200, 0, -200, 200, 0],
    N: [0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1], I: [0, 1, 2, 0, 2, 3] });
  const NB = scene.bodies.length;
  let NO = 0, itemObjects = [];
  const ACTOR_COLORS = [[0.38, 0.62, 0.88], [0.62, 0.78, 0.55], [0.85, 0.75, 0.45], [0.8, 0.55, 0.85]];
  const OBJ_COLOR = [0.9, 0.45, 0.12];
  const MASKED_COLOR = [0.75, 0.3, 0.3];

  let item = null, actors = [], length = 1;
  function selectItem(k) {
    item = scene.items[k];
    itemObjects = item.objects.map((i) => objects[i]);
    NO = itemObjects.length;
    actors = item.actors.map((a) => ({
      a, body: f32(a.body), obj: f32(a.obj), value: f32(a.value),
    }));
    length = Math.max(1, ...item.actors.map((a) => a.frames));
    scrub.max = String(length - 1);
    setFrame(0);
    labels.innerHTML = "";
    actors.forEach((x, i) => {
      const d = document.createElement("div");
      d.className = "label";
      d.id = "label" + i;
      labels.appendChild(d);
    });
    skillEl.textContent = item.skill + (item.note ? "\n" + item.note : "");
    layout();
  }
  function frameOf(x, f) {
    return Math.min(f, x.a.frames - 1);
  }
  function rootOf(x, f) {
    const o = frameOf(x, f) * NB * 7;
    return [x.body[o], x.body[o + 1], x.body[o + 2]];
  }

  // ---------- camera ----------
  const cam = { az: -1.2, el: 0.25, dist: 4.5, pan: [0, 0, 0] };
  let drag = null;
  canvas.addEventListener("mousedown", (e) => { drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 }; });
  window.addEventListener("mouseup", () => { drag = null; });
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      // move the target along the camera's right and up directions
      const s = cam.dist * 0.0015, ra = [-Math.sin(cam.az), Math.cos(cam.az)];
      cam.pan[0] -= ra[0] * dx * s;
      cam.pan[1] -= ra[1] * dx * s;
      cam.pan[2] += dy * s;
    } else {
      cam.az -= dx * 0.008;
      cam.el = Math.max(-0.1, Math.min(1.5, cam.el + dy * 0.006));
    }
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    cam.dist = Math.max(0.8, Math.min(40, cam.dist * Math.exp(e.deltaY * 0.001)));
  }, { passive: false });

  // ---------- controls ----------
  const itemSel = document.getElementById("item"), playBtn = document.getElementById("play");
  const speedSel = document.getElementById("speed"), scrub = document.getElementById("scrub");
  const frameEl = document.getElementById("frame"), labels = document.getElementById("labels");
  const skillEl = document.getElementById("skill"), followEl = document.getElementById("follow");
  const overlayEl = document.getElementById("overlay");
  overlayEl.addEventListener("change", () => layout());
  scene.items.forEach((it, k) => {
    const o = document.createElement("option");
    o.value = String(k);
    o.textContent = it.title;
    itemSel.appendChild(o);
  });
  let playing = true, clock = 0, last = performance.now();
  function setFrame(f) {
    state.frame = Math.max(0, Math.min(length - 1, f));
    clock = state.frame;
    scrub.value = String(state.frame);
  }
  itemSel.addEventListener("change", () => selectItem(Number(itemSel.value)));
  playBtn.addEventListener("click", () => { playing = !playing; playBtn.textContent = playing ? "pause" : "play"; });
  scrub.addEventListener("input", () => setFrame(Number(scrub.value)));
  window.addEventListener("keydown", (e) => {
    if (e.key === " ") { playBtn.click(); e.preventDefault(); }
    else if (e.key === "ArrowRight") { setFrame(state.frame + 1); }
    else if (e.key === "ArrowLeft") { setFrame(state.frame - 1); }
  });

  let W = 1, H = 1;
  function layout() {
    const dpr = window.devicePixelRatio || 1;
    W = Math.max(1, Math.floor(canvas.clientWidth * dpr));
    H = Math.max(1, Math.floor(canvas.clientHeight * dpr));
    canvas.width = W;
    canvas.height = H;
    const groups = viewGroups();
    groups.forEach((g, v) => g.forEach((i, k) => {
      const d = document.getElementById("label" + i);
      if (d) {
        d.style.left = (8 + (v * canvas.clientWidth) / groups.length) + "px";
        d.style.top = (8 + 44 * k) + "px";
      }
    }));
    // resizing clears the drawing buffer: draw again at once, so that no
    // frame (or screenshot) shows an empty canvas
    if (item) render();
  }
  window.addEventListener("resize", layout);

  // ---------- drawing ----------
  function drawActor(x, f, shadow, alpha) {
    const fi = frameOf(x, f);
    const masked = x.a.masked[fi] === 1;
    const color = masked ? MASKED_COLOR : ACTOR_COLORS[actors.indexOf(x) % ACTOR_COLORS.length];
    const ob = fi * NB * 7;
    for (let b = 0; b < NB; b++) {
      const o = ob + b * 7;
      const bt = [x.body[o], x.body[o + 1], x.body[o + 2]];
      const bq = [x.body[o + 3], x.body[o + 4], x.body[o + 5], x.body[o + 6]];
      for (const g of geoms[b]) {
        const p = qrot(bq, g.pos);
        draw(g.mesh, [bt[0] + p[0], bt[1] + p[1], bt[2] + p[2]], qmul(bq, g.quat), color, alpha, shadow);
      }
    }
    const oo = fi * NO * 7;
    const culled = gl.isEnabled(gl.CULL_FACE);
    gl.disable(gl.CULL_FACE); // object meshes: both sides
    for (let k = 0; k < NO; k++) {
      const o = oo + k * 7;
      draw(itemObjects[k], [x.obj[o], x.obj[o + 1], x.obj[o + 2]],
        [x.obj[o + 3], x.obj[o + 4], x.obj[o + 5], x.obj[o + 6]], OBJ_COLOR, alpha, shadow);
    }
    if (culled) gl.enable(gl.CULL_FACE);
  }
  // the figures of each view: one each side by side, or all in one view
  // (the first solid, the others as ghosts) with "overlay"
  function viewGroups() {
    if (!actors.length) return [[]];
    if (overlayEl.checked) return [actors.map((x, i) => i)];
    return actors.map((x, i) => [i]);
  }
  function render() {
    const groups = viewGroups();
    const n = groups.length;
    const f = state.frame;
    gl.enable(gl.SCISSOR_TEST);
    gl.enable(gl.DEPTH_TEST);
    gl.enable(gl.CULL_FACE);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    for (let i = 0; i < n; i++) {
      const x0 = Math.floor((i * W) / n), x1 = Math.floor(((i + 1) * W) / n);
      gl.viewport(x0, 0, x1 - x0, H);
      gl.scissor(x0, 0, x1 - x0, H);
      gl.clearColor(0.13, 0.14, 0.16, 1);
      gl.clearStencil(0);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT | gl.STENCIL_BUFFER_BIT);
      const members = groups[i].map((k) => actors[k]);
      const x = members[0];
      const r = x && followEl.checked ? rootOf(x, f) : [0, 0, 0.9];
      const at = [r[0] + cam.pan[0], r[1] + cam.pan[1], 0.9 + cam.pan[2]];
      const ce = Math.cos(cam.el);
      const eye = [at[0] + cam.dist * ce * Math.cos(cam.az), at[1] + cam.dist * ce * Math.sin(cam.az),
        at[2] + cam.dist * Math.sin(cam.el)];
      gl.uniformMatrix4fv(loc.uVP, false, matmul(perspective(0.8, (x1 - x0) / H, 0.1, 120),
        lookAt(eye, at, [0, 0, 1])));
      gl.uniform1f(loc.uGround, 1);
      gl.disable(gl.CULL_FACE);
      draw(ground, [0, 0, 0], [0, 0, 0, 1], [at[0], at[1], 0], 1, false);
      gl.enable(gl.CULL_FACE);
      gl.uniform1f(loc.uGround, 0);
      if (!x) continue;
      // shadows: flattened onto the ground over it (no depth test, no
      // culling: flattened triangles face either way), each pixel darkened
      // once through the stencil
      gl.disable(gl.DEPTH_TEST);
      gl.disable(gl.CULL_FACE);
      gl.enable(gl.STENCIL_TEST);
      gl.stencilFunc(gl.EQUAL, 0, 0xff);
      gl.stencilOp(gl.KEEP, gl.KEEP, gl.INCR);
      for (const m of members) drawActor(m, f, true, 1);
      gl.disable(gl.STENCIL_TEST);
      gl.enable(gl.CULL_FACE);
      gl.enable(gl.DEPTH_TEST);
      drawActor(x, f, false, 1);
      // ghosts after the solid figure, without writing depth
      gl.depthMask(false);
      for (const m of members.slice(1)) drawActor(m, f, false, 0.38);
      gl.depthMask(true);
      members.forEach((m, k) => {
        const d = document.getElementById("label" + groups[i][k]);
        if (!d) return;
        const fi = frameOf(m, f);
        const masked = m.a.masked[fi] === 1;
        let t = m.a.name + (k > 0 ? " (ghost)" : "") + (f >= m.a.frames ? " (ended)" : "") + (masked ? "  masked" : "");
        if (m.value.length > fi && !Number.isNaN(m.value[fi])) t += "\n" + m.a.value_name + " " + m.value[fi].toFixed(3);
        d.textContent = t;
        d.className = masked ? "label masked" : "label";
      });
    }
    gl.disable(gl.SCISSOR_TEST);
    frameEl.textContent = "frame " + f + " / " + (length - 1) + "  " + (f / item.fps).toFixed(2) + " s";
  }
  // a timer rather than requestAnimationFrame, so playback also advances
  // where no display drives animation frames (headless checks)
  function tick() {
    try {
      const now = performance.now();
      const dt = Math.min(0.1, (now - last) / 1000);
      last = now;
      if (playing && item) {
        clock += dt * item.fps * Number(speedSel.value);
        if (clock >= length) clock = 0;
        const f = Math.floor(clock);
        if (f !== state.frame) {
          // frames advanced by playback, counted across loops (the counter
          // element carries it as data-played, for checks)
          state.played++;
          frameEl.dataset.played = String(state.played);
        }
        state.frame = f;
        scrub.value = String(state.frame);
      }
      const dpr = window.devicePixelRatio || 1;
      if (Math.floor(canvas.clientWidth * dpr) !== W || Math.floor(canvas.clientHeight * dpr) !== H) layout();
      else if (item) render();
    } catch (e) {
      fail("error: " + e.message);
      return;
    }
    setTimeout(tick, 1000 / 60);
  }
  // the page's address may pick the start: #item=K&frame=F&paused
  const hash = new URLSearchParams(location.hash.slice(1));
  if (!scene.items.length) fail("error: the scene has no item");
  else {
    const k = Math.max(0, Math.min(scene.items.length - 1, Number(hash.get("item")) || 0));
    itemSel.value = String(k);
    selectItem(k);
    if (hash.has("frame")) setFrame(Number(hash.get("frame")) || 0);
    if (hash.has("overlay")) { overlayEl.checked = true; layout(); }
    if (hash.has("paused")) playBtn.click();
  }
  tick();
})();

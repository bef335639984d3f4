// The report page's behaviour: loupe, zoom, live relight, the rig from above, provenance
// tables, and the self-test (report.html#selftest) the test suite reads back from the DOM.
(function () {
  "use strict";
  var data = JSON.parse(document.getElementById("psscan-data").textContent);
  var report = data.report || {};
  var $ = function (id) { return document.getElementById(id); };

  // ---- loupe and zoom -------------------------------------------------------------------
  // A view's loupe source arrives as JPEG bands of rows (encoded side by side); they are
  // drawn once, unscaled at whole-pixel rows, into one canvas, so the loupe's magnified draw
  // has no seams between bands. Null until every band has decoded.
  var loupeCanvases = {};

  // A view's bands, each with its first row.
  function loupeBands(name) {
    return Array.prototype.slice.call(document.querySelectorAll("img.loupe-src"))
      .filter(function (img) { return img.getAttribute("data-view") === name; })
      .map(function (img) { return { img: img, row: +img.getAttribute("data-row") }; });
  }

  function loupeSource(name) {
    if (loupeCanvases[name]) return loupeCanvases[name];
    var bands = loupeBands(name);
    if (!bands.length || bands.some(function (b) { return !b.img.complete || !b.img.naturalWidth; })) return null;
    var canvas = document.createElement("canvas");
    canvas.width = bands[0].img.naturalWidth;
    canvas.height = bands.reduce(function (rows, b) { return Math.max(rows, b.row + b.img.naturalHeight); }, 0);
    var ctx = canvas.getContext("2d");
    bands.forEach(function (b) { ctx.drawImage(b.img, 0, b.row); });
    loupeCanvases[name] = canvas;
    return canvas;
  }

  // What the self-test reports of a view's loupe source: its size, its black pixels (a band
  // missing or misplaced leaves black rows), its bands, and the largest difference between
  // each band drawn alone and its rows in the whole (one band drawn over another's rows).
  function loupeCheck(name) {
    var canvas = loupeSource(name);
    if (!canvas) return null;
    var w = canvas.width, h = canvas.height;
    var whole = canvas.getContext("2d").getImageData(0, 0, w, h).data;
    var out = { width: w, height: h, black_pixels: 0, bands: 0, band_max_difference: 0 };
    for (var i = 0; i < whole.length; i += 4) {
      if (whole[i] + whole[i + 1] + whole[i + 2] === 0) out.black_pixels++;
    }
    loupeBands(name).forEach(function (b) {
      var alone = document.createElement("canvas");
      alone.width = b.img.naturalWidth;
      alone.height = b.img.naturalHeight;
      var actx = alone.getContext("2d");
      actx.drawImage(b.img, 0, 0);
      var band = actx.getImageData(0, 0, alone.width, alone.height).data;
      for (var k = 0; k < band.length; k++) {
        var d = Math.abs(band[k] - whole[b.row * w * 4 + k]);
        if (d > out.band_max_difference) out.band_max_difference = d;
      }
      out.bands++;
    });
    return out;
  }

  function setupLoupe(name) {
    var view = $("img-" + name);
    if (!view) return;
    var loupe = $("loupe"), canvas = $("loupe-canvas"), ctx = canvas.getContext("2d");
    var label = $("loupe-label");
    view.addEventListener("click", function () { view.parentNode.classList.toggle("zoomed"); });
    view.addEventListener("mouseleave", function () { loupe.hidden = true; });
    view.addEventListener("mousemove", function (e) {
      var src = loupeSource(name);
      if (!src) return;
      var rect = view.getBoundingClientRect();
      var fx = (e.clientX - rect.left) / rect.width * src.width;
      var fy = (e.clientY - rect.top) / rect.height * src.height;
      var span = 60 / data.loupe_step;
      ctx.imageSmoothingEnabled = false;
      ctx.fillStyle = "#000";
      ctx.fillRect(0, 0, canvas.width, canvas.height);
      ctx.drawImage(src, fx - span / 2, fy - span / 2, span, span, 0, 0, canvas.width, canvas.height);
      label.textContent = name + " x " + Math.floor(fx * data.loupe_step) + " y " + Math.floor(fy * data.loupe_step) +
        (data.loupe_step > 1 ? " (every " + data.loupe_step + "th pixel" : " (full resolution") +
        ", JPEG q" + data.loupe_quality + ")";
      loupe.style.left = (e.clientX + 20) + "px";
      loupe.style.top = (e.clientY - 120) + "px";
      loupe.hidden = false;
    });
  }

  // ---- relight ---------------------------------------------------------------------------
  var state = {
    light: [data.defaults.light[0], data.defaults.light[1], data.defaults.light[2]],
    brdf: data.defaults.brdf, roughness: data.defaults.roughness, exposure: data.defaults.exposure
  };
  var gl = null, program = null, drawRelight = function () {};

  function compile(type, id) {
    var shader = gl.createShader(type);
    gl.shaderSource(shader, $(id).textContent);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(id + ": " + gl.getShaderInfoLog(shader));
    return shader;
  }

  function texture(unit, img) {
    var tex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, img);
    [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER].forEach(function (p) { gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST); });
    [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T].forEach(function (p) { gl.texParameteri(gl.TEXTURE_2D, p, gl.CLAMP_TO_EDGE); });
  }

  function setupRelight() {
    var canvas = $("relight-canvas");
    if (!data.relight) { canvas.parentNode.hidden = true; return "no textures"; }
    var albedo = $("img-albedo"), normal = $("img-normal");
    canvas.width = albedo.naturalWidth;
    canvas.height = albedo.naturalHeight;
    gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, alpha: false, antialias: false, premultipliedAlpha: false });
    if (!gl) {
      canvas.parentNode.insertAdjacentHTML("beforebegin", "<p class=\"absent\">this browser offers no WebGL: the relight cannot draw</p>");
      return "no webgl";
    }
    program = gl.createProgram();
    gl.attachShader(program, compile(gl.VERTEX_SHADER, "vertex-shader"));
    gl.attachShader(program, compile(gl.FRAGMENT_SHADER, "fragment-shader"));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error("relight program: " + gl.getProgramInfoLog(program));
    gl.useProgram(program);
    var buffer = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    var at = gl.getAttribLocation(program, "position");
    gl.enableVertexAttribArray(at);
    gl.vertexAttribPointer(at, 2, gl.FLOAT, false, 0, 0);
    texture(0, albedo);
    texture(1, normal);
    var u = function (name) { return gl.getUniformLocation(program, name); };
    gl.uniform1i(u("albedoTex"), 0);
    gl.uniform1i(u("normalTex"), 1);
    gl.uniform2f(u("size"), canvas.width, canvas.height);
    gl.uniform1f(u("background"), data.background);
    drawRelight = function () {
      gl.viewport(0, 0, canvas.width, canvas.height);
      gl.uniform3f(u("light"), state.light[0], state.light[1], state.light[2]);
      gl.uniform1i(u("brdf"), state.brdf === "cloth" ? 1 : 0);
      gl.uniform1f(u("roughness"), state.roughness);
      gl.uniform1f(u("exposure"), state.exposure);
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
      drawHemisphere();
    };
    return null;
  }

  // ---- the hemisphere, the LEDs, the frames ----------------------------------------------
  var lights = Array.isArray(report.lights) ? report.lights : [];
  var selected = -1;

  function unit(v) {
    var n = Math.hypot(v[0], v[1], v[2]) || 1;
    return [v[0] / n, v[1] / n, v[2] / n];
  }

  function drawHemisphere() {
    var c = $("hemisphere"), ctx = c.getContext("2d"), r = c.width / 2 - 12, cx = c.width / 2, cy = c.height / 2;
    ctx.clearRect(0, 0, c.width, c.height);
    ctx.strokeStyle = "#888";
    ctx.beginPath(); ctx.arc(cx, cy, r, 0, 2 * Math.PI); ctx.stroke();
    ctx.strokeStyle = "#ddd";
    [30, 60].forEach(function (deg) { ctx.beginPath(); ctx.arc(cx, cy, r * Math.sin(deg * Math.PI / 180), 0, 2 * Math.PI); ctx.stroke(); });
    ctx.beginPath(); ctx.moveTo(cx - r, cy); ctx.lineTo(cx + r, cy); ctx.moveTo(cx, cy - r); ctx.lineTo(cx, cy + r); ctx.stroke();
    ctx.fillStyle = "#555"; ctx.font = "11px sans-serif";
    ctx.fillText("+X", cx + r - 14, cy - 4); ctx.fillText("+Y", cx + 4, cy - r + 12);
    lights.forEach(function (led, k) {
      var d = unit(led.direction);
      ctx.fillStyle = k === selected ? "#e33" : "#f5b400";
      ctx.strokeStyle = "#333";
      ctx.beginPath(); ctx.arc(cx + d[0] * r, cy - d[1] * r, 6, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
      if (lights.length <= 24) { ctx.fillStyle = "#333"; ctx.fillText(String(k), cx + d[0] * r + 7, cy - d[1] * r - 5); }
    });
    var l = unit(state.light);
    ctx.fillStyle = "#07c";
    ctx.beginPath(); ctx.arc(cx + l[0] * r, cy - l[1] * r, 8, 0, 2 * Math.PI); ctx.fill();
    var elevation = Math.asin(Math.max(-1, Math.min(1, l[2]))) * 180 / Math.PI;
    var azimuth = Math.atan2(l[1], l[0]) * 180 / Math.PI;
    $("light-readout").textContent = "light (" + l.map(function (v) { return v.toFixed(3); }).join(", ") + "), elevation " +
      elevation.toFixed(1) + " deg, azimuth " + azimuth.toFixed(1) + " deg";
  }

  function showFrame(k) {
    var label = $("frame-label"), canvas = $("frame-canvas"), strip = $("img-frames"), f = data.frames || {};
    var led = lights[k] || {};
    var name = "light " + k + (led.frame ? " (" + led.frame + ")" : "");
    if (!strip || !f.count) {
      label.textContent = name + ": " + (f.why || "frames not available");
      return;
    }
    canvas.width = f.tile_w; canvas.height = f.tile_h;
    canvas.getContext("2d").drawImage(strip, k * f.tile_w, 0, f.tile_w, f.tile_h, 0, 0, f.tile_w, f.tile_h);
    label.textContent = name + ": the frame as captured (downscaled, one exposure for all frames)";
  }

  function setupHemisphere() {
    var c = $("hemisphere"), dragging = false;
    function toLight(e) {
      var rect = c.getBoundingClientRect(), r = c.width / 2 - 12;
      var x = ((e.clientX - rect.left) * c.width / rect.width - c.width / 2) / r;
      var y = -((e.clientY - rect.top) * c.height / rect.height - c.height / 2) / r;
      return [x, y];
    }
    function hitLed(p) {
      var best = -1, bestD = 10 / (c.width / 2 - 12);
      lights.forEach(function (led, k) {
        var d = unit(led.direction), dist = Math.hypot(d[0] - p[0], d[1] - p[1]);
        if (dist < bestD) { best = k; bestD = dist; }
      });
      return best;
    }
    function move(p) {
      var len = Math.hypot(p[0], p[1]);
      if (len > 0.999) { p = [p[0] / len * 0.999, p[1] / len * 0.999]; len = 0.999; }
      state.light = [p[0], p[1], Math.sqrt(1 - len * len)];
      drawRelight(); drawHemisphere();
    }
    c.addEventListener("pointerdown", function (e) {
      var p = toLight(e), k = hitLed(p);
      if (k >= 0) {
        selected = k;
        state.light = unit(lights[k].direction);
        showFrame(k);
        drawRelight(); drawHemisphere();
        return;
      }
      dragging = true; c.setPointerCapture(e.pointerId); move(p);
    });
    c.addEventListener("pointermove", function (e) { if (dragging) move(toLight(e)); });
    c.addEventListener("pointerup", function () { dragging = false; });
    var brdf = $("brdf"), rough = $("roughness"), exposure = $("exposure");
    brdf.value = state.brdf; rough.value = state.roughness; exposure.value = state.exposure;
    function sync() {
      state.brdf = brdf.value; state.roughness = +rough.value; state.exposure = +exposure.value;
      $("roughness-value").textContent = state.roughness.toFixed(2);
      $("exposure-value").textContent = state.exposure.toFixed(2);
      drawRelight();
    }
    [brdf, rough, exposure].forEach(function (el) { el.addEventListener("input", sync); });
    sync();
    if (lights.length === 0) $("frame-label").textContent = "the report lists no lights: the rig cannot be drawn";
    else if (!(data.frames || {}).count) $("frame-label").textContent = (data.frames || {}).why || "frames not available";
    else $("frame-label").textContent = "click an LED to see its frame";
    drawHemisphere();
  }

  // ---- provenance -----------------------------------------------------------------------
  function esc(s) { return String(s).replace(/[&<>"]/g, function (c) { return { "&": "&amp;", "<": "&lt;", ">": "&gt;", "\"": "&quot;" }[c]; }); }

  function fmt(v) {
    if (typeof v === "number") return Number.isInteger(v) ? String(v) : (Math.abs(v) >= 1e-3 && Math.abs(v) < 1e6 ? v.toFixed(4) : v.toExponential(3));
    if (v === null) return "none";
    return String(v);
  }

  function flatten(prefix, v, rows) {
    if (v && typeof v === "object" && !Array.isArray(v)) {
      Object.keys(v).forEach(function (k) { flatten(prefix ? prefix + "." + k : k, v[k], rows); });
    } else if (Array.isArray(v) && v.some(function (x) { return x && typeof x === "object"; })) {
      v.forEach(function (x, i) { flatten(prefix + "[" + i + "]", x, rows); });
    } else {
      rows.push([prefix, Array.isArray(v) ? "[" + v.map(fmt).join(", ") + "]" : fmt(v)]);
    }
    return rows;
  }

  function table(title, value, note) {
    if (value === undefined || value === null) return "";
    var rows = flatten("", value, []).map(function (r) {
      var cls = /sha256|hash/.test(r[0]) ? " class=\"hash\"" : "";
      return "<tr><th>" + esc(r[0] || "value") + "</th><td" + cls + ">" + esc(r[1]) + "</td></tr>";
    }).join("");
    return "<div><h3>" + esc(title) + "</h3>" + (note ? "<p class=\"note\">" + esc(note) + "</p>" : "") + "<table class=\"kv\">" + rows + "</table></div>";
  }

  function lightsTable() {
    if (!lights.length) return "";
    var rows = lights.map(function (l, k) {
      var d = unit(l.direction);
      return "<tr><td>" + k + "</td><td>" + esc(l.frame || "") + "</td><td class=\"hash\">" + esc(l.sha256 || "") +
        "</td><td>" + d.map(function (v) { return v.toFixed(3); }).join(", ") + "</td></tr>";
    }).join("");
    return "<div><h3>frames and lights</h3><table class=\"kv\"><tr><th>light</th><th>frame</th><th>sha256</th><th>direction</th></tr>" + rows + "</table></div>";
  }

  function histogram() {
    var h = report.normal_error_histogram;
    if (!h || !h.counts || !h.counts.length) return "<p class=\"note\">no ground truth for this set: no error histogram</p>";
    var w = 640, ht = 180, n = h.counts.length, max = Math.max.apply(null, h.counts) || 1, bw = (w - 40) / n;
    var bars = h.counts.map(function (c, i) {
      var bh = c / max * (ht - 30);
      return "<rect x=\"" + (30 + i * bw).toFixed(1) + "\" y=\"" + (ht - 20 - bh).toFixed(1) + "\" width=\"" + Math.max(bw - 1, 1).toFixed(1) +
        "\" height=\"" + bh.toFixed(1) + "\" fill=\"#4a7\"><title>" + (i * h.bin_deg).toFixed(3) + "-" + ((i + 1) * h.bin_deg).toFixed(3) + " deg: " + c + "</title></rect>";
    }).join("");
    var ticks = [0, n / 2, n].map(function (i) {
      return "<text x=\"" + (30 + i * bw).toFixed(1) + "\" y=\"" + (ht - 5) + "\" font-size=\"11\" text-anchor=\"middle\">" + (i * h.bin_deg).toFixed(2) + "</text>";
    }).join("");
    return "<h3>normal error against ground truth (deg)</h3><svg width=\"" + w + "\" height=\"" + ht + "\" role=\"img\">" + bars + ticks +
      "<line x1=\"30\" x2=\"" + (w - 10) + "\" y1=\"" + (ht - 20) + "\" y2=\"" + (ht - 20) + "\" stroke=\"#333\"/></svg>" +
      "<p class=\"note\">" + h.pixels + " pixels; " + (h.above || 0) + " above " + (n * h.bin_deg).toFixed(2) + " deg not drawn</p>";
  }

  function provenance() {
    if (data.report_error) {
      $("provenance-tables").innerHTML = "<p class=\"absent\">" + esc(data.report_error) + "</p>";
      $("histogram").innerHTML = "";
      return;
    }
    var overview = { capture: report.capture, rig: report.rig, width: report.width, height: report.height, psscan_version: report.psscan_version };
    $("provenance-tables").innerHTML =
      table("capture", overview) +
      table("calibration bundle", report.calibration || "none: solved with the set's hand-measured rig") +
      table("bundle the set cites (not used)", report.calibration_cited_by_set) +
      table("camera settings", report.camera) +
      lightsTable() +
      table("decoding", report.decode) +
      table("options", report.options) +
      table("timings per stage (s)", report.timings_s) +
      table("pixels per status", report.pixels) +
      table("solved pixels per fit", report.fits) +
      table("errors against ground truth", report.truth) +
      table("normals against ground truth (benchmark mask)", report.normal_truth) +
      table("region", report.region) +
      table("outputs", report.outputs);
    $("histogram").innerHTML = histogram();
  }

  // ---- self-test -------------------------------------------------------------------------
  function params() {
    var out = {};
    location.hash.replace(/^#/, "").split("&").forEach(function (kv) {
      var p = kv.split("=");
      out[p[0]] = p.length > 1 ? decodeURIComponent(p[1]) : true;
    });
    return out;
  }

  function canvasSnapshot() {
    var c = $("relight-canvas");
    var px = new Uint8Array(c.width * c.height * 4);
    gl.readPixels(0, 0, c.width, c.height, gl.RGBA, gl.UNSIGNED_BYTE, px);
    var lit = 0;
    for (var i = 0; i < px.length; i += 4) if (px[i] !== data.background || px[i + 1] !== data.background || px[i + 2] !== data.background) lit++;
    return { png: c.toDataURL("image/png"), lit: lit };
  }

  // Whether an image decodes: drawing it forces the decode; a broken one has no size or
  // throws.
  function decodes(img) {
    if (!img.complete || !img.naturalWidth) return false;
    try {
      var c = document.createElement("canvas");
      c.width = c.height = 1;
      var ctx = c.getContext("2d");
      ctx.drawImage(img, img.naturalWidth - 1, img.naturalHeight - 1, 1, 1, 0, 0, 1, 1);
      ctx.getImageData(0, 0, 1, 1);
      return true;
    } catch (e) {
      return false;
    }
  }

  // Runs synchronously inside the load handler, so Chromium's --dump-dom, which prints the DOM
  // once loading is done, always sees the results.
  function selftest(setupError, loadMs) {
    var p = params(), out = { load_ms: loadMs, webgl: !!gl, setup_error: setupError };
    var imgs = Array.prototype.slice.call(document.images);
    var t0 = performance.now();
    out.images = imgs.length;
    out.images_failed = imgs.filter(function (img) { return !decodes(img); }).map(function (img) { return img.id || img.alt; });
    out.decode_ms = performance.now() - t0;
    out.loupe = { albedo: loupeCheck("albedo"), normal: loupeCheck("normal") };
    (function () {
      if (gl) {
        if (p.light) state.light = p.light.split(",").map(Number);
        if (p.brdf) state.brdf = p.brdf;
        if (p.roughness) state.roughness = +p.roughness;
        if (p.exposure) state.exposure = +p.exposure;
        drawRelight();
        var first = canvasSnapshot();
        out.canvas_png = first.png;
        out.lit_pixels = first.lit;
        state.light = [-state.light[0], -state.light[1], state.light[2]];
        drawRelight();
        out.changed_when_light_moved = canvasSnapshot().png !== first.png;
        out.gl_error = gl.getError();
        out.renderer = gl.getParameter(gl.RENDERER);
      }
      out.errors = window.psscanErrors.slice();
      var pre = $("selftest");
      pre.textContent = "SELFTEST-BEGIN" + JSON.stringify(out) + "SELFTEST-END";
      pre.hidden = false;
    })();
  }

  window.addEventListener("load", function () {
    var loadMs = performance.now();
    var setupError = null;
    try {
      provenance();
      setupLoupe("albedo");
      setupLoupe("normal");
      // Derived maps zoom on click; they have no full-resolution loupe source.
      setupLoupe("height");
      setupLoupe("roughness");
      setupError = setupRelight();
      setupHemisphere();
      drawRelight();
    } catch (e) {
      setupError = String(e && e.message || e);
      console.error(setupError);
    }
    if (/^#selftest/.test(location.hash)) selftest(setupError, loadMs);
  });
})();

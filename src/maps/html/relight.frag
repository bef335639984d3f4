// The relight, texel for texel the arithmetic of src/maps/html/relight.rs (keep them in step).
precision highp float;
uniform sampler2D albedoTex;
uniform sampler2D normalTex;
uniform vec2 size;
uniform vec3 light;
uniform int brdf;        // 0: GGX (seed 004 Appendix A), 1: cloth (eq. 23)
uniform float roughness;
uniform float exposure;
uniform float background;

const float PI = 3.14159265358979;
const float F0 = 0.04;
const float VELVET_AMPLITUDE = 4.0;

float srgbToLinear(float c) {
  return c <= 0.04045 ? c / 12.92 : pow((c + 0.055) / 1.055, 2.4);
}

float linearToSrgb(float c) {
  c = clamp(c, 0.0, 1.0);
  return c <= 0.0031308 ? c * 12.92 : 1.055 * pow(c, 1.0 / 2.4) - 0.055;
}

float ggxV1(float m2, float x) {
  return 1.0 / (x + sqrt(m2 + (1.0 - m2) * x * x));
}

float ggxSpecular(float m, float nl, float nh, float nv, float fresnel) {
  float m2 = m * m;
  float t = nh * nh * (m2 - 1.0) + 1.0;
  float d = m2 / (PI * t * t);
  return d * fresnel * ggxV1(m2, nl) * ggxV1(m2, nv);
}

float velvet(float alpha, float nh) {
  float a2 = alpha * alpha;
  float sin2 = 1.0 - nh * nh;
  float lobe = 0.0;
  if (sin2 > 1e-4) {
    lobe = VELVET_AMPLITUDE * exp(-(nh * nh / sin2) / a2) / (sin2 * sin2);
  }
  return (1.0 + lobe) / (PI * (1.0 + VELVET_AMPLITUDE * a2));
}

float shade(float albedo, float nl, float nh, float nv, float lh) {
  float fresnel = F0 + (1.0 - F0) * pow(1.0 - lh, 5.0);
  float f;
  if (brdf == 0) {
    f = albedo / PI + ggxSpecular(roughness, nl, nh, nv, fresnel);
  } else {
    f = (1.0 - fresnel) * albedo / PI
      + fresnel * velvet(roughness, nh) / (4.0 * (nl + nv - nl * nv));
  }
  return PI * exposure * f * nl;
}

void main() {
  // Image row 0 is the top; the framebuffer's y runs up.
  vec2 uv = vec2(gl_FragCoord.x / size.x, 1.0 - gl_FragCoord.y / size.y);
  vec3 a = texture2D(albedoTex, uv).rgb;
  vec3 raw = texture2D(normalTex, uv).rgb * 2.0 - 1.0;
  if (raw.z <= 0.01) {
    gl_FragColor = vec4(vec3(background / 255.0), 1.0);
    return;
  }
  vec3 n = normalize(raw);
  vec3 l = normalize(light);
  vec3 v = vec3(0.0, 0.0, 1.0);
  vec3 h = normalize(l + v);
  float nl = max(dot(n, l), 0.0);
  float nv = max(dot(n, v), 1e-4);
  float nh = clamp(dot(n, h), 0.0, 1.0);
  float lh = clamp(dot(l, h), 0.0, 1.0);
  vec3 outc = vec3(0.0);
  if (nl > 0.0) {
    outc = vec3(shade(srgbToLinear(a.r), nl, nh, nv, lh),
                shade(srgbToLinear(a.g), nl, nh, nv, lh),
                shade(srgbToLinear(a.b), nl, nh, nv, lh));
  }
  gl_FragColor = vec4(linearToSrgb(outc.r), linearToSrgb(outc.g), linearToSrgb(outc.b), 1.0);
}

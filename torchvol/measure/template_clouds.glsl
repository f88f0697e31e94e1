// Seed 002's complete cloud template, verbatim (only line breaks added). ShaderToy conventions:
// iChannel0 = a 256x256 RGBA8 noise texture, LINEAR filter, REPEAT wrap.
// Volumetric Cloud Renderer — ShaderToy Template
#define NUM_STEPS 80
#define SUN_DIR normalize(vec3(-0.7, 0.0, -0.7))
#define CLOUD_BOTTOM -1.0
#define CLOUD_TOP 2.0
#define WIND_SPEED 0.1
#define DENSITY_SCALE 1.75
#define DENSITY_THRESHOLD 0.01
float noise(vec3 x) {
vec3 p = floor(x);
vec3 f = fract(x);
f = f * f * (3.0 - 2.0 * f);
vec2 uv = (p.xy + vec2(37.0, 239.0) * p.z) + f.xy;
vec2 rg = textureLod(iChannel0, (uv + 0.5) / 256.0, 0.0).yx;
return mix(rg.x, rg.y, f.z) * 2.0 - 1.0;
}
float map(vec3 p, int lod) {
vec3 q = p - vec3(0.0, WIND_SPEED, 1.0) * iTime;
float f;
f = 0.50000 * noise(q);
q *= 2.02;
if (lod >= 2) f += 0.25000 * noise(q);
q *= 2.03;
if (lod >= 3) f += 0.12500 * noise(q);
q *= 2.01;
if (lod >= 4) f += 0.06250 * noise(q);
q *= 2.02;
if (lod >= 5) f += 0.03125 * noise(q);
return clamp(1.5 - p.y - 2.0 + DENSITY_SCALE * f, 0.0, 1.0);
}
vec3 lightSample(vec3 pos, float den, int lod) {
float dif = clamp((den - map(pos + 0.3 * SUN_DIR, lod)) / 0.6, 0.0, 1.0);
vec3 lin = vec3(1.0, 0.6, 0.3) * dif + vec3(0.91, 0.98, 1.05);
vec3 col = mix(vec3(1.0, 0.95, 0.8), vec3(0.25, 0.3, 0.35), den);
return col * lin;
}
vec4 raymarch(vec3 ro, vec3 rd, vec3 bgcol, ivec2 px) {
float tmin = (CLOUD_BOTTOM - ro.y) / rd.y;
float tmax = (CLOUD_TOP - ro.y) / rd.y;
if (tmin > tmax) {
float tmp = tmin;
tmin = tmax;
tmax = tmp;
}
if (tmax < 0.0) return vec4(0.0);
tmin = max(tmin, 0.0);
tmax = min(tmax, 60.0);
float t = tmin + 0.1 * fract(sin(float(px.x * 73 + px.y * 311)) * 43758.5453);
vec4 sum = vec4(0.0);
for (int i = 0;
i < NUM_STEPS;
i++) {
float dt = max(0.05, 0.02 * t);
int lod = 5 - int(log2(1.0 + t * 0.5));
vec3 pos = ro + t * rd;
float den = map(pos, lod);
if (den > DENSITY_THRESHOLD) {
vec3 litCol = lightSample(pos, den, lod);
litCol = mix(litCol, bgcol, 1.0 - exp(-0.003 * t * t));
vec4 col = vec4(litCol, den);
col.a *= 0.4;
col.rgb *= col.a;
sum += col * (1.0 - sum.a);
}
t += dt;
if (t > tmax || sum.a > 0.99) break;
}
return clamp(sum, 0.0, 1.0);
}
mat3 setCamera(vec3 ro, vec3 ta, float cr) {
vec3 cw = normalize(ta - ro);
vec3 cp = vec3(sin(cr), cos(cr), 0.0);
vec3 cu = normalize(cross(cw, cp));
vec3 cv = normalize(cross(cu, cw));
return mat3(cu, cv, cw);
}
void mainImage(out vec4 fragColor, in vec2 fragCoord) {
vec2 p = (2.0 * fragCoord - iResolution.xy) / iResolution.y;
vec2 m = iMouse.xy / iResolution.xy;
vec3 ro = 4.0 * normalize(vec3(sin(3.0 * m.x), 0.8 * m.y, cos(3.0 * m.x)));
ro.y += 0.5;
vec3 ta = vec3(0.0, -1.0, 0.0);
mat3 ca = setCamera(ro, ta, 0.07 * cos(0.25 * iTime));
vec3 rd = ca * normalize(vec3(p, 1.5));
float sun = clamp(dot(SUN_DIR, rd), 0.0, 1.0);
vec3 bgcol = vec3(0.6, 0.71, 0.75) - rd.y * 0.2 * vec3(1.0, 0.5, 1.0) + 0.075;
bgcol += 0.2 * vec3(1.0, 0.6, 0.1) * pow(sun, 8.0);
vec4 res = raymarch(ro, rd, bgcol, ivec2(fragCoord - 0.5));
vec3 col = bgcol * (1.0 - res.a) + res.rgb;
col += vec3(0.2, 0.08, 0.04) * pow(sun, 3.0);
col = smoothstep(0.15, 1.1, col);
fragColor = vec4(col, 1.0);
}

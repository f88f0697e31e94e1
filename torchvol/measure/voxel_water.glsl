// Seed 001 "Water Surface Rendering": its wave normal, Fresnel, reflect and refract, evaluated on a
// grid of water points and view rays (one per pixel). uMode: 0 the ray, 1 normal + fresnel,
// 2 reflect, 3 refract into the water (1/1.33), 4 refract out of it from below (1.33: TIR -> 0).
uniform int uMode;

void mainImage(out vec4 fragColor, in vec2 fragCoord) {
    vec3 waterPos = vec3((fragCoord.x - 0.5 * iResolution.x) * 0.37, 0.0, fragCoord.y * 0.29);
    vec3 rd = normalize(vec3(fragCoord.x / iResolution.x - 0.5, -(0.02 + fragCoord.y / iResolution.y), 0.3));
    vec3 waterNormal = vec3(0.0, 1.0, 0.0);
    vec2 waveXZ = waterPos.xz;
    waterNormal.x += 0.05 * sin(waveXZ.x * 3.0 + iTime);
    waterNormal.z += 0.05 * cos(waveXZ.y * 2.0 + iTime * 0.7);
    waterNormal = normalize(waterNormal);
    float fresnel = 0.04 + 0.96 * pow(1.0 - max(dot(waterNormal, -rd), 0.0), 5.0);
    if (uMode == 0) fragColor = vec4(rd, 0.0);
    else if (uMode == 1) fragColor = vec4(waterNormal, fresnel);
    else if (uMode == 2) fragColor = vec4(reflect(rd, waterNormal), 0.0);
    else if (uMode == 3) fragColor = vec4(refract(rd, waterNormal, 1.0 / 1.33), 0.0);
    else fragColor = vec4(refract(rd * vec3(1.0, -1.0, 1.0), -waterNormal, 1.33), 0.0);
}

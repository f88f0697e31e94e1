// Seed 001 Steps 1–8 (ShaderToy form; wrap with torchvol.testing.glsl.shadertoy_source): the
// voxel-carved-box preset. One change from the seed's text: on an exact tie the DDA steps exactly
// one axis, the first of x, y, z (the seed's step()/lessThanEqual form moves two at once).
// uMode 0 writes the colour; 1 writes the hit position (w = 1 where a voxel was hit).
uniform vec3 uEye;
uniform vec3 uSunDir;
uniform vec3 uSky;
uniform int uMode;

#define MAX_RAY_STEPS 64
#define MAX_SHADOW_STEPS 32

float sdSphere(vec3 p, float r) { return length(p) - r; }
float sdBox(vec3 p, vec3 b) {
    vec3 d = abs(p) - b;
    return min(max(d.x, max(d.y, d.z)), 0.0) + length(max(d, 0.0));
}

bool getVoxel(ivec3 c) {
    vec3 p = vec3(c) + vec3(0.5);
    float d = max(-sdSphere(p, 7.5), sdBox(p, vec3(6.0)));
    return d < 0.0;
}

// exactly one axis: the first of x, y, z among the nearest
vec3 stepMask(vec3 sd) {
    bool mx = sd.x <= min(sd.y, sd.z);
    bool my = !mx && sd.y <= sd.z;
    bool mz = !mx && !my;
    return vec3(mx, my, mz);
}

float castShadow(vec3 ro, vec3 rd) {
    vec3 pos = floor(ro);
    vec3 ri = 1.0 / rd;
    vec3 rs = sign(rd);
    vec3 dis = (pos - ro + 0.5 + rs * 0.5) * ri;
    for (int i = 0; i < MAX_SHADOW_STEPS; i++) {
        if (getVoxel(ivec3(pos))) return 0.0;
        vec3 mm = stepMask(dis);
        dis += mm * rs * ri;
        pos += mm * rs;
    }
    return 1.0;
}

float vertexAo(vec2 side, float corner) {
    return (side.x + side.y + max(corner, side.x * side.y)) / 3.0;
}

float occ(vec3 p) { return getVoxel(ivec3(p)) ? 1.0 : 0.0; }

vec4 voxelAo(vec3 pos, vec3 d1, vec3 d2) {
    vec4 side = vec4(occ(pos + d1), occ(pos + d2), occ(pos - d1), occ(pos - d2));
    vec4 corner = vec4(occ(pos + d1 + d2), occ(pos - d1 + d2), occ(pos - d1 - d2), occ(pos + d1 - d2));
    vec4 ao;
    ao.x = vertexAo(side.xy, corner.x);
    ao.y = vertexAo(side.yz, corner.y);
    ao.z = vertexAo(side.zw, corner.z);
    ao.w = vertexAo(side.wx, corner.w);
    return 1.0 - ao;
}

void mainImage(out vec4 fragColor, in vec2 fragCoord) {
    // Step 1: camera
    vec2 screenPos = (fragCoord.xy / iResolution.xy) * 2.0 - 1.0;
    vec3 cameraDir = vec3(0.0, 0.0, 0.8);
    vec3 cameraPlaneU = vec3(1.0, 0.0, 0.0);
    vec3 cameraPlaneV = vec3(0.0, 1.0, 0.0) * iResolution.y / iResolution.x;
    vec3 rayDir = normalize(cameraDir + screenPos.x * cameraPlaneU + screenPos.y * cameraPlaneV);
    vec3 rayPos = uEye;
    // Step 2: DDA set-up
    ivec3 mapPos = ivec3(floor(rayPos));
    vec3 deltaDist = abs(1.0 / rayDir);
    vec3 rayStep = sign(rayDir);
    vec3 sideDist = (sign(rayDir) * (vec3(mapPos) - rayPos) + (sign(rayDir) * 0.5) + 0.5) * deltaDist;
    // Step 3: traversal
    vec3 mask = vec3(0.0);
    bool hit = false;
    for (int i = 0; i < MAX_RAY_STEPS; i++) {
        if (getVoxel(mapPos)) { hit = true; break; }
        mask = stepMask(sideDist);
        sideDist += mask * deltaDist;
        mapPos += ivec3(mask * rayStep);
    }
    if (!hit) {
        fragColor = uMode == 1 ? vec4(0.0) : vec4(uSky, 1.0);
        return;
    }
    // Step 5: face normal and three tones
    vec3 normal = -mask * rayStep;
    float tone = dot(mask, vec3(0.5, 1.0, 0.75));
    // Step 6: hit position and face UV
    float t = dot(sideDist - deltaDist, mask);
    vec3 hitPos = rayPos + rayDir * t;
    vec3 uvw = hitPos - vec3(mapPos);
    vec2 uv = vec2(dot(mask * uvw.yzx, vec3(1.0)), dot(mask * uvw.zxy, vec3(1.0)));
    // Step 7: neighbour AO
    vec4 ambient = voxelAo(vec3(mapPos) - rayStep * mask, mask.zxy, mask.yzx);
    float ao = mix(mix(ambient.z, ambient.w, uv.x), mix(ambient.y, ambient.x, uv.x), uv.y);
    ao = pow(ao, 1.0 / 3.0);
    // Step 8: DDA shadow ray and Lambert sun
    float shadow = castShadow(hitPos + normal * 0.01, uSunDir);
    float diffuse = max(dot(normal, uSunDir), 0.0) * shadow;
    vec3 col = vec3(1.0) * tone * ao * (vec3(0.3) + vec3(0.7) * diffuse);
    fragColor = uMode == 1 ? vec4(hitPos, 1.0) : vec4(col, 1.0);
}

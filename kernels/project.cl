/* EWA projection of 3D Gaussians (forward and backward), one work-item per Gaussian.
 * cam = [R (9, row-major), t (3), fx, fy, cx, cy]: world-to-camera, OpenCV axes. */
#include "common.h"

inline void quat_to_rot(float w, float x, float y, float z, float *R)
{
    R[0] = 1.f - 2.f * (y * y + z * z); R[1] = 2.f * (x * y - w * z); R[2] = 2.f * (x * z + w * y);
    R[3] = 2.f * (x * y + w * z); R[4] = 1.f - 2.f * (x * x + z * z); R[5] = 2.f * (y * z - w * x);
    R[6] = 2.f * (x * z - w * y); R[7] = 2.f * (y * z + w * x); R[8] = 1.f - 2.f * (x * x + y * y);
}

/* Everything the backward pass needs again, recomputed rather than stored. */
typedef struct {
    float pc[3];    /* camera-space mean */
    float q[4];     /* normalised quaternion */
    float qnorm;
    float Rq[9];    /* rotation of the Gaussian */
    float M[9];     /* Rq * diag(s) */
    float RM[9];    /* Rcam * M */
    float J[6];     /* EWA Jacobian (2x3) */
    float T[6];     /* J * RM */
    float a, b, c;  /* 2D covariance incl. EPS2D */
    int clamp_x, clamp_y;
} Proj;

/* Returns 0 when the Gaussian is culled. */
inline int project_one(__global const float *means, __global const float *quats,
                       __global const float *scales, __global const float *cam, int i,
                       int width, int height, float near, float far, Proj *P, float *ext)
{
    float m0 = means[3 * i], m1 = means[3 * i + 1], m2 = means[3 * i + 2];
    float qw = quats[4 * i], qx = quats[4 * i + 1], qy = quats[4 * i + 2], qz = quats[4 * i + 3];
    float s0 = scales[3 * i], s1 = scales[3 * i + 1], s2 = scales[3 * i + 2];
    if (!(isfinite(m0) && isfinite(m1) && isfinite(m2) && isfinite(qw) && isfinite(qx) &&
          isfinite(qy) && isfinite(qz) && isfinite(s0) && isfinite(s1) && isfinite(s2)))
        return 0;
    float qn = sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
    if (!(qn > 0.0f) || !isfinite(qn))
        return 0;
    for (int r = 0; r < 3; ++r)
        P->pc[r] = cam[3 * r] * m0 + cam[3 * r + 1] * m1 + cam[3 * r + 2] * m2 + cam[9 + r];
    float x = P->pc[0], y = P->pc[1], z = P->pc[2];
    if (!(z >= near && z <= far))
        return 0;
    P->qnorm = qn;
    P->q[0] = qw / qn; P->q[1] = qx / qn; P->q[2] = qy / qn; P->q[3] = qz / qn;
    quat_to_rot(P->q[0], P->q[1], P->q[2], P->q[3], P->Rq);
    float s[3] = {s0, s1, s2};
    for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k)
            P->M[3 * r + k] = P->Rq[3 * r + k] * s[k];
    for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k)
            P->RM[3 * r + k] = cam[3 * r] * P->M[k] + cam[3 * r + 1] * P->M[3 + k] + cam[3 * r + 2] * P->M[6 + k];
    float fx = cam[12], fy = cam[13], cx = cam[14], cy = cam[15];
    float tfx = 0.5f * width / fx, tfy = 0.5f * height / fy;
    float lxp = (width - cx) / fx + FRUSTUM_MARGIN * tfx, lxn = cx / fx + FRUSTUM_MARGIN * tfx;
    float lyp = (height - cy) / fy + FRUSTUM_MARGIN * tfy, lyn = cy / fy + FRUSTUM_MARGIN * tfy;
    float u = x / z, v = y / z;
    P->clamp_x = !(u >= -lxn && u <= lxp);
    P->clamp_y = !(v >= -lyn && v <= lyp);
    u = clamp(u, -lxn, lxp);
    v = clamp(v, -lyn, lyp);
    P->J[0] = fx / z; P->J[1] = 0.f; P->J[2] = -fx * u / z;
    P->J[3] = 0.f; P->J[4] = fy / z; P->J[5] = -fy * v / z;
    for (int r = 0; r < 2; ++r)
        for (int k = 0; k < 3; ++k)
            P->T[3 * r + k] = P->J[3 * r] * P->RM[k] + P->J[3 * r + 1] * P->RM[3 + k] + P->J[3 * r + 2] * P->RM[6 + k];
    P->a = P->T[0] * P->T[0] + P->T[1] * P->T[1] + P->T[2] * P->T[2] + EPS2D;
    P->b = P->T[0] * P->T[3] + P->T[1] * P->T[4] + P->T[2] * P->T[5];
    P->c = P->T[3] * P->T[3] + P->T[4] * P->T[4] + P->T[5] * P->T[5] + EPS2D;
    float det = P->a * P->c - P->b * P->b;
    if (!(det > 0.0f) || !isfinite(det))
        return 0;
    float mid = 0.5f * (P->a + P->c);
    float lam = mid + sqrt(fmax(mid * mid - det, EIGEN_FLOOR));
    float r = ceil(SIGMA_RADIUS * sqrt(lam));
    if (!(r > 0.0f))
        return 0;
    r = fmin(r, (float)MAX_RADIUS_PX);
    float mx = fx * x / z + cx, my = fy * y / z + cy;
    if (!(mx + r > 0.0f && mx - r < width && my + r > 0.0f && my - r < height))
        return 0;
    *ext = r;
    return 1;
}

__kernel void project_fwd(const int n, __global const float *means, __global const float *quats,
                          __global const float *scales, __global const float *cam,
                          const int width, const int height, const float near, const float far,
                          __global float *means2d, __global float *conics,
                          __global float *depths, __global int *radii)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    Proj P;
    float r;
    if (!project_one(means, quats, scales, cam, i, width, height, near, far, &P, &r)) {
        means2d[2 * i] = 0.f; means2d[2 * i + 1] = 0.f;
        conics[3 * i] = 0.f; conics[3 * i + 1] = 0.f; conics[3 * i + 2] = 0.f;
        depths[i] = 0.f;
        radii[i] = 0;
        return;
    }
    float det = P.a * P.c - P.b * P.b;
    float z = P.pc[2];
    means2d[2 * i] = cam[12] * P.pc[0] / z + cam[14];
    means2d[2 * i + 1] = cam[13] * P.pc[1] / z + cam[15];
    conics[3 * i] = P.c / det;
    conics[3 * i + 1] = -P.b / det;
    conics[3 * i + 2] = P.a / det;
    depths[i] = z;
    radii[i] = (int)r;
}

__kernel void project_bwd(const int n, __global const float *means, __global const float *quats,
                          __global const float *scales, __global const float *cam,
                          const int width, const int height, const float near, const float far,
                          __global const int *radii, __global const float *conics,
                          __global const float *v_means2d, __global const float *v_conics,
                          __global const float *v_depths,
                          __global float *v_means, __global float *v_quats, __global float *v_scales)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    Proj P;
    float r;
    if (radii[i] <= 0 || !project_one(means, quats, scales, cam, i, width, height, near, far, &P, &r)) {
        for (int k = 0; k < 3; ++k) { v_means[3 * i + k] = 0.f; v_scales[3 * i + k] = 0.f; }
        for (int k = 0; k < 4; ++k) v_quats[4 * i + k] = 0.f;
        return;
    }
    const float fx = cam[12], fy = cam[13];
    const float x = P.pc[0], y = P.pc[1], z = P.pc[2];
    /* conic = inv(cov2d): dL/dcov = -Q G Q with G the symmetric gradient of Q. */
    float A = conics[3 * i], B = conics[3 * i + 1], C = conics[3 * i + 2];
    float gA = v_conics[3 * i], gB = 0.5f * v_conics[3 * i + 1], gC = v_conics[3 * i + 2];
    float QG00 = A * gA + B * gB, QG01 = A * gB + B * gC, QG10 = B * gA + C * gB, QG11 = B * gB + C * gC;
    float V00 = -(QG00 * A + QG01 * B), V01 = -(QG00 * B + QG01 * C), V11 = -(QG10 * B + QG11 * C);
    /* cov2d = T T^T  =>  dL/dT = 2 V T */
    float dT[6];
    for (int k = 0; k < 3; ++k) {
        dT[k] = 2.f * (V00 * P.T[k] + V01 * P.T[3 + k]);
        dT[3 + k] = 2.f * (V01 * P.T[k] + V11 * P.T[3 + k]);
    }
    /* T = J RM: dL/dJ = dT RM^T, dL/dRM = J^T dT */
    float dJ[6];
    for (int rr = 0; rr < 2; ++rr)
        for (int k = 0; k < 3; ++k)
            dJ[3 * rr + k] = dT[3 * rr] * P.RM[3 * k] + dT[3 * rr + 1] * P.RM[3 * k + 1] + dT[3 * rr + 2] * P.RM[3 * k + 2];
    float dRM[9];
    for (int rr = 0; rr < 3; ++rr)
        for (int k = 0; k < 3; ++k)
            dRM[3 * rr + k] = P.J[rr] * dT[k] + P.J[3 + rr] * dT[3 + k];
    /* RM = Rcam M: dL/dM = Rcam^T dRM */
    float dM[9];
    for (int rr = 0; rr < 3; ++rr)
        for (int k = 0; k < 3; ++k)
            dM[3 * rr + k] = cam[rr] * dRM[k] + cam[3 + rr] * dRM[3 + k] + cam[6 + rr] * dRM[6 + k];
    /* M = Rq diag(s) */
    float s[3] = {scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]};
    float G[9];
    for (int k = 0; k < 3; ++k) {
        v_scales[3 * i + k] = dM[k] * P.Rq[k] + dM[3 + k] * P.Rq[3 + k] + dM[6 + k] * P.Rq[6 + k];
        for (int rr = 0; rr < 3; ++rr)
            G[3 * rr + k] = dM[3 * rr + k] * s[k];
    }
    float w = P.q[0], qx = P.q[1], qy = P.q[2], qz = P.q[3];
    float gw = 2.f * (-qz * G[1] + qy * G[2] + qz * G[3] - qx * G[5] - qy * G[6] + qx * G[7]);
    float gx = 2.f * (qy * G[1] + qz * G[2] + qy * G[3] - 2.f * qx * G[4] - w * G[5] + qz * G[6] + w * G[7] - 2.f * qx * G[8]);
    float gy = 2.f * (-2.f * qy * G[0] + qx * G[1] + w * G[2] + qx * G[3] + qz * G[5] - w * G[6] + qz * G[7] - 2.f * qy * G[8]);
    float gz = 2.f * (-2.f * qz * G[0] - w * G[1] + qx * G[2] + w * G[3] - 2.f * qz * G[4] + qy * G[5] + qx * G[6] + qy * G[7]);
    float dot = w * gw + qx * gx + qy * gy + qz * gz;
    v_quats[4 * i] = (gw - w * dot) / P.qnorm;
    v_quats[4 * i + 1] = (gx - qx * dot) / P.qnorm;
    v_quats[4 * i + 2] = (gy - qy * dot) / P.qnorm;
    v_quats[4 * i + 3] = (gz - qz * dot) / P.qnorm;
    /* camera-space mean: through J, the projected mean and the depth */
    float u = -P.J[2] * z / fx, v = -P.J[5] * z / fy; /* the (clamped) x/z, y/z */
    float vx = 0.f, vy = 0.f, vz = 0.f;
    vz += dJ[0] * (-fx / (z * z)) + dJ[4] * (-fy / (z * z));
    vz += dJ[2] * (fx * u / (z * z)) + dJ[5] * (fy * v / (z * z));
    if (!P.clamp_x) { vx += dJ[2] * (-fx / (z * z)); vz += dJ[2] * (fx * x / (z * z * z)); }
    if (!P.clamp_y) { vy += dJ[5] * (-fy / (z * z)); vz += dJ[5] * (fy * y / (z * z * z)); }
    float gmx = v_means2d[2 * i], gmy = v_means2d[2 * i + 1];
    vx += fx / z * gmx;
    vy += fy / z * gmy;
    vz += -fx * x / (z * z) * gmx - fy * y / (z * z) * gmy + v_depths[i];
    for (int k = 0; k < 3; ++k)
        v_means[3 * i + k] = cam[k] * vx + cam[3 + k] * vy + cam[6 + k] * vz;
}

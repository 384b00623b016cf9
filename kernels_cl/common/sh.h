/* sh.h — real spherical harmonics up to degree 8 (81 coefficients), evaluation and adjoint.
 *
 * Convention (matches 3D Gaussian Splatting for degree <= 3; tested against scipy):
 *   index k = l*l + l + m,  -l <= m <= l
 *   Y_{l,0}  = Y_l^0
 *   Y_{l,m}  = sqrt(2) Re(Y_l^m)      m > 0
 *   Y_{l,m}  = sqrt(2) Im(Y_l^|m|)    m < 0
 * where Y_l^m are the complex SH *with* the Condon-Shortley phase (scipy.special.sph_harm_y).
 * So Y_{1,-1} = -c y, Y_{1,0} = c z, Y_{1,1} = -c x with c = sqrt(3/(4 pi)).
 *
 * Evaluation as polynomials of the unit direction d = (x, y, z) (no trig, no division):
 *   C_m + i S_m = (x + i y)^m                    (C_m = sin^m(theta) cos(m phi), S_m likewise)
 *   Q_l^m(z) = P_l^m(z) / sin^m(theta):   Q_m^m = (-1)^m (2m-1)!!,  Q_{m+1}^m = (2m+1) z Q_m^m,
 *                                           Q_l^m = ((2l-1) z Q_{l-1}^m - (l+m-1) Q_{l-2}^m) / (l-m)
 *   Y_{l,0} = K_l^0 Q_l^0,  Y_{l,m} = sqrt2 K_l^m Q_l^m C_m,  Y_{l,-m} = sqrt2 K_l^m Q_l^m S_m
 *   K_l^m = sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!)
 *
 * sh_eval(deg, d, Y)        writes Y[0 .. (deg+1)^2 - 1]. d must be unit for these to be the SH;
 *                           for other d it is the polynomial extension.
 * sh_eval_vjp(deg, d, v_Y)  returns v_d = sum_k v_Y[k] dY_k/dd of that polynomial (callers chain
 *                           it through their normalisation's vjp, which removes the radial part):
 *   dQ_l^m/dz by differentiating the recurrence; dC_m/dx = m C_{m-1}, dC_m/dy = -m S_{m-1},
 *   dS_m/dx = m S_{m-1}, dS_m/dy = m C_{m-1}.
 *
 * SH_BAND_A[l]: the Ramamoorthi-Hanrahan band factors of the clamped cosine, so that the
 * irradiance of radiance L = sum c_k Y_k is E(n) = sum_k A_{l(k)} c_k Y_k(n):
 *   A_0 = pi, A_1 = 2 pi/3, odd l > 1: 0,
 *   even l: 2 pi (-1)^(l/2-1) / ((l+2)(l-1)) * l! / (2^l ((l/2)!)^2).
 */
#ifndef TRIPLET_SH_H
#define TRIPLET_SH_H

#include "real.h"

#define SH_MAX_DEGREE 8
#define SH_MAX_COEFFS 81

/* sqrt(2) K_l^m for m > 0, K_l^0 for m == 0, at index l(l+1)/2 + m. */
__constant REAL SH_KLM[45] = {
    0.28209479177387814, 0.4886025119029199, 0.48860251190292, 0.6307831305050401,
    0.36418281019735976, 0.18209140509867988, 0.7463526651802308, 0.3046971996429772,
    0.09635371475468515, 0.03933623932844291, 0.8462843753216345, 0.2676186174229157,
    0.063078313050504, 0.016858388283618388, 0.005960340337611203, 0.9356025796273888,
    0.2415715473043717, 0.045652731285460234, 0.009318824751147628, 0.002196468058075176,
    0.0006945841871324552, 1.0171072362820548, 0.22195099524523101, 0.03509353369580661,
    0.005848922282634435, 0.0010678622237644956, 0.00022766899107568562, 6.57223766418388e-05,
    1.0925484305920792, 0.20647224590289676, 0.028097313806030647, 0.003973560225074135,
    0.0005990367431114117, 9.983945718523528e-05, 1.958012847746254e-05, 5.233009453691466e-06,
    1.1631066229203195, 0.1938511038200533, 0.023169638523677944, 0.0028519853513317033,
    0.00036818972564450655, 5.1058728265780266e-05, 7.878532816214047e-06, 1.4384167144950456e-06,
    3.596041786237614e-07};

__constant REAL SH_BAND_A[9] = {
    3.141592653589793, 2.0943951023931953, 0.7853981633974483, 0.0, -0.1308996938995747, 0.0,
    0.04908738521234052, 0.0, -0.02454369260617026};

inline void sh_eval(const int deg, const REAL3 d, REAL* Y)
{
    const REAL x = d.x, y = d.y, z = d.z;
    REAL C = (REAL)1, S = (REAL)0, qmm = (REAL)1;
    for (int m = 0; m <= deg; ++m) {
        if (m > 0) {
            const REAL Cn = x * C - y * S;
            S = x * S + y * C;
            C = Cn;
            qmm *= -(REAL)(2 * m - 1);
        }
        REAL q2 = (REAL)0, q1 = (REAL)0;
        for (int l = m; l <= deg; ++l) {
            REAL q;
            if (l == m) q = qmm;
            else if (l == m + 1) q = (REAL)(2 * m + 1) * z * qmm;
            else q = ((REAL)(2 * l - 1) * z * q1 - (REAL)(l + m - 1) * q2) / (REAL)(l - m);
            const REAL kq = SH_KLM[l * (l + 1) / 2 + m] * q;
            const int c = l * l + l;
            if (m == 0) {
                Y[c] = kq;
            } else {
                Y[c + m] = kq * C;
                Y[c - m] = kq * S;
            }
            q2 = q1;
            q1 = q;
        }
    }
}

inline REAL3 sh_eval_vjp(const int deg, const REAL3 d, const REAL* v_Y)
{
    const REAL x = d.x, y = d.y, z = d.z;
    REAL C = (REAL)1, S = (REAL)0, qmm = (REAL)1;
    REAL v_x = (REAL)0, v_y = (REAL)0, v_z = (REAL)0;
    for (int m = 0; m <= deg; ++m) {
        const REAL Cp = C, Sp = S; /* C_{m-1}, S_{m-1} */
        if (m > 0) {
            const REAL Cn = x * C - y * S;
            S = x * S + y * C;
            C = Cn;
            qmm *= -(REAL)(2 * m - 1);
        }
        REAL q2 = (REAL)0, q1 = (REAL)0, dq2 = (REAL)0, dq1 = (REAL)0;
        REAL v_C = (REAL)0, v_S = (REAL)0;
        for (int l = m; l <= deg; ++l) {
            REAL q, dq;
            if (l == m) {
                q = qmm;
                dq = (REAL)0;
            } else if (l == m + 1) {
                q = (REAL)(2 * m + 1) * z * qmm;
                dq = (REAL)(2 * m + 1) * qmm;
            } else {
                const REAL a = (REAL)(2 * l - 1), b = (REAL)(l + m - 1), inv = (REAL)1 / (REAL)(l - m);
                q = (a * z * q1 - b * q2) * inv;
                dq = (a * (q1 + z * dq1) - b * dq2) * inv;
            }
            const REAL K = SH_KLM[l * (l + 1) / 2 + m];
            const int c = l * l + l;
            if (m == 0) {
                v_z += v_Y[c] * K * dq;
            } else {
                v_z += K * dq * (v_Y[c + m] * C + v_Y[c - m] * S);
                v_C += K * q * v_Y[c + m];
                v_S += K * q * v_Y[c - m];
            }
            q2 = q1;
            q1 = q;
            dq2 = dq1;
            dq1 = dq;
        }
        if (m > 0) {
            const REAL fm = (REAL)m;
            v_x += fm * (v_C * Cp + v_S * Sp);
            v_y += fm * (v_S * Cp - v_C * Sp);
        }
    }
    return (REAL3)(v_x, v_y, v_z);
}

#endif /* TRIPLET_SH_H */

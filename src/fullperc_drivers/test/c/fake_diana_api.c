/*
 * Test double of Agile Robots' libDianaApi.so: the functions the diana_api backend binds, with the
 * signatures and the packed srv_net_st of DianaAPI.h (#pragma pack(1)).
 *
 * The "controller" state is set by the test (FakeDiana_SetJoints); getTcpPos returns the flange pose
 * [x y z rx ry rz] (rotation vector) computed here in C from the modified-DH table written out
 * independently of the Python model — so the test can compare two implementations. getDH returns the
 * table in the vendor's array order (a, alpha, d, theta), optionally with d1 altered by the test.
 * Build: gcc -shared -fPIC -O1 -o libfake_diana.so fake_diana_api.c -lm
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#define API __attribute__((visibility("default")))

#pragma pack(1)
typedef struct _SrvNetSt {
    char SrvIp[32];
    unsigned short LocHeartbeatPort;
    unsigned short LocRobotStatePort;
    unsigned short LocSrvPort;
    unsigned short LocRealtimeSrvPort;
    unsigned short LocPassThroughSrvPort;
} srv_net_st;
#pragma pack()

typedef void (*FNCERRORCALLBACK)(int e, const char *strIpAddress);
typedef void (*FNCSTATECALLBACK)(void *pinfo, const char *strIpAddress);

static const double PI = 3.14159265358979323846;
/* alpha_{i-1}, a_{i-1}, d_i, theta_i (reference/diana_eval.md, Diana 7) */
static double g_alpha[7] = {PI, PI / 2, -PI / 2, PI / 2, -PI / 2, -PI / 2, -PI / 2};
static double g_a[7] = {0, 0, 0, 0.065, -0.0528, -0.0122, 0.087};
static double g_d[7] = {-0.2856, 0, -0.4586, 0, -0.4554, 0, -0.1169};
static double g_theta[7] = {0, 0, 0, 0, 0, PI, 0};

static char g_ip[32] = "192.168.10.75";
static int g_connected = 0, g_fail_reads = 0, g_last_error = 0, g_init_calls = 0, g_destroy_calls = 0;
static double g_q[7];
static unsigned short g_seen_ports[5];
static int g_nan = 0;

API void FakeDiana_Configure(const char *ip) {
    strncpy(g_ip, ip, 31); g_connected = 0; g_fail_reads = 0; g_init_calls = 0; g_destroy_calls = 0; g_nan = 0;
    for (int i = 0; i < 7; i++) g_q[i] = 0.0;
    g_d[0] = -0.2856;
}
API void FakeDiana_SetJoints(const double q[7]) { for (int i = 0; i < 7; i++) g_q[i] = q[i]; }
API void FakeDiana_FailReads(int n) { g_fail_reads = n; }
API void FakeDiana_SetNaN(int on) { g_nan = on; }
API void FakeDiana_SetD1(double d1) { g_d[0] = d1; }
API int FakeDiana_InitCalls(void) { return g_init_calls; }
API int FakeDiana_DestroyCalls(void) { return g_destroy_calls; }
API int FakeDiana_Connected(void) { return g_connected; }
API int FakeDiana_SrvNetSize(void) { return (int)sizeof(srv_net_st); }
API int FakeDiana_SeenPort(int i) { return g_seen_ports[i]; }

API void initSrvNetInfo(srv_net_st *p) { memset(p, 0, sizeof(*p)); }
API int initSrv(FNCERRORCALLBACK fnError, FNCSTATECALLBACK fnState, srv_net_st *p) {
    (void)fnError; (void)fnState;
    g_init_calls++;
    g_seen_ports[0] = p->LocHeartbeatPort; g_seen_ports[1] = p->LocRobotStatePort; g_seen_ports[2] = p->LocSrvPort;
    g_seen_ports[3] = p->LocRealtimeSrvPort; g_seen_ports[4] = p->LocPassThroughSrvPort;
    if (strncmp(p->SrvIp, g_ip, 32) != 0) { g_last_error = -2001; return -1; }
    g_connected = 1;
    return 0;
}
API int destroySrv(const char *ip) { (void)ip; g_destroy_calls++; g_connected = 0; return 0; }
API int getLastError(const char *ip) { (void)ip; return g_last_error; }
API const char *formatError(int e, const char *ip) {
    (void)ip;
    if (e == -2001) return "socket error: robot unreachable";
    if (e == -2002) return "lost robot state";
    return "no error";
}
API int getJointPos(double *joints, const char *ip) {
    (void)ip;
    if (!g_connected) { g_last_error = -2002; return -1; }
    if (g_fail_reads > 0) { g_fail_reads--; g_last_error = -2002; return -1; }
    for (int i = 0; i < 7; i++) joints[i] = g_nan && i == 3 ? NAN : g_q[i];
    return 0;
}

static void matmul4(const double A[16], const double B[16], double C[16]) { /* row-major */
    for (int r = 0; r < 4; r++)
        for (int c = 0; c < 4; c++) {
            double s = 0;
            for (int k = 0; k < 4; k++) s += A[r * 4 + k] * B[k * 4 + c];
            C[r * 4 + c] = s;
        }
}

API int getTcpPos(double *pose, const char *ip) {
    (void)ip;
    if (!g_connected) return -1;
    double T[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1}, L[16], N[16];
    for (int i = 0; i < 7; i++) {
        double ca = cos(g_alpha[i]), sa = sin(g_alpha[i]);
        double ct = cos(g_theta[i] + g_q[i]), st = sin(g_theta[i] + g_q[i]);
        /* RotX(alpha) TransX(a) RotZ(theta) TransZ(d), multiplied out (Craig 3.6) */
        double Li[16] = {ct, -st, 0, g_a[i],
                         st * ca, ct * ca, -sa, -sa * g_d[i],
                         st * sa, ct * sa, ca, ca * g_d[i],
                         0, 0, 0, 1};
        memcpy(L, Li, sizeof(L));
        matmul4(T, L, N);
        memcpy(T, N, sizeof(T));
    }
    pose[0] = T[3]; pose[1] = T[7]; pose[2] = T[11];
    /* rotation vector from R */
    double tr = T[0] + T[5] + T[10];
    double c = (tr - 1) / 2; if (c > 1) c = 1; if (c < -1) c = -1;
    double ang = acos(c);
    double rx = T[9] - T[6], ry = T[2] - T[8], rz = T[4] - T[1];
    double s = sqrt(rx * rx + ry * ry + rz * rz);
    if (s > 1e-9 && ang < PI - 1e-6) {
        pose[3] = rx / s * ang; pose[4] = ry / s * ang; pose[5] = rz / s * ang;
    } else if (ang < 1e-9) {
        pose[3] = pose[4] = pose[5] = 0;
    } else { /* angle ~ pi: axis from the diagonal of (R + I)/2 */
        double xx = sqrt(fmax(0, (T[0] + 1) / 2)), yy = sqrt(fmax(0, (T[5] + 1) / 2)), zz = sqrt(fmax(0, (T[10] + 1) / 2));
        if (xx >= yy && xx >= zz) { yy = copysign(yy, T[1]); zz = copysign(zz, T[2]); }
        else if (yy >= zz) { xx = copysign(xx, T[1]); zz = copysign(zz, T[6]); }
        else { xx = copysign(xx, T[2]); yy = copysign(yy, T[6]); }
        pose[3] = xx * ang; pose[4] = yy * ang; pose[5] = zz * ang;
    }
    return 0;
}

API int getDH(double *a, double *alpha, double *d, double *theta, const char *ip) {
    (void)ip;
    if (!g_connected) return -1;
    for (int i = 0; i < 7; i++) { a[i] = g_a[i]; alpha[i] = g_alpha[i]; d[i] = g_d[i]; theta[i] = g_theta[i]; }
    return 0;
}

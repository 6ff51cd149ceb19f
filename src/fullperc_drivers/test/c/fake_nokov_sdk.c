/*
 * Test double of NOKOV's libnokov_sdk.so (flat C API used by the vendor's Python/C# wrappers).
 *
 * Struct layouts are transcribed from NokovSDKTypes.h "version 1.3.0.12" (NOKOV-MOCAP/mocap_nokov,
 * deps/nokov_sdk/include). The library plays a scripted scenario from its own thread through the data
 * callback, like the real SDK's receive thread:
 *   - rigid body 1 "base" is described from the start;
 *   - rigid body 2 "tool" appears at frame `appear_at`: it is added to the descriptions and a
 *     RigidBodyChange/ActionAdd notification is sent (frames before that do not contain it);
 *   - "tool" is lost for frames [lost_from, lost_to): coordinates UNDEFINED, params 0, 0 markers;
 *   - frame numbers jump by `gap` + 1 once, at frame index `gap_at` (dropped frames);
 *   - iTimeStamp = capture time on CLOCK_MONOTONIC (a device clock offset from the host's realtime
 *     clock) in units of `ts_unit_ns`; fLatency = `latency_s` (seconds).
 * If the environment variable FAKE_NOKOV_START_FILE is set, playback starts only once that file exists
 * (lets a multi-process test start the frames after its subscribers are matched).
 * Environment for a node in another process, which the FakeNokov_* functions cannot reach (read at Initialize):
 * FAKE_NOKOV_FRAMES=n plays n frames (default 300, at most TRUTH_MAX); FAKE_NOKOV_RATE_HZ=r at r Hz (default 200;
 * a system test on a busy machine asks for less); FAKE_NOKOV_STEADY=1 plays a steady scene
 * (both bodies at rest at their frame-0 poses, "tool" never lost, no frame-number gap): what a system test of the
 * whole graph needs, where the static links are averaged from bodies at rest (test/test_bringup_graph.py).
 * Test-only FakeNokov_* functions configure the scenario and return the truth (capture time on the
 * host realtime clock of each frame index, and the positions in mm as a function of the frame index).
 * Build: gcc -shared -fPIC -O1 -pthread -o libfake_nokov.so fake_nokov_sdk.c
 */
#include <math.h>
#include <pthread.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#define API __attribute__((visibility("default")))

#define MAX_MODELS 200
#define MAX_RIGIDBODIES 1000
#define MAX_NAMELENGTH 256
#define MAX_SKELETONS 100
#define MAX_SKELRIGIDBODIES 200
#define MAX_LABELED_MARKERS 1000
#define MAX_ANALOG_CHANNELS 32
#define MAX_MSG_LENGTH 100
#define UNDEFINED 999999.9999

typedef float MarkerData[3];

typedef struct { int ID; float x; float y; float z; float size; short params; } sMarker;
typedef struct { char szName[MAX_NAMELENGTH]; int nMarkers; char **szMarkerNames; } sMarkerSetDescription;
typedef struct { char szName[MAX_NAMELENGTH]; int nMarkers; MarkerData *Markers; } sMarkerSetData;
typedef struct {
    char szName[MAX_NAMELENGTH]; int ID; int parentID;
    float offsetx, offsety, offsetz; float qx, qy, qz, qw;
} sRigidBodyDescription;
typedef struct sRigidBodyData {
    int ID; float x, y, z; float qx, qy, qz, qw; int nMarkers; MarkerData *Markers; int *MarkerIDs;
    float *MarkerSizes; float MeanError; short params;
} sRigidBodyData;
typedef struct {
    char szName[MAX_NAMELENGTH]; int skeletonID; int nRigidBodies;
    sRigidBodyDescription RigidBodies[MAX_SKELRIGIDBODIES];
} sSkeletonDescription;
typedef struct { int skeletonID; int nRigidBodies; sRigidBodyData *RigidBodyData; } sSkeletonData;
typedef struct {
    int ID; int scale; float fWidth; float fLength; float Position[3]; float Electrical[3];
    float Orientation[3][3]; float fCalMat[8][8]; float fCorners[4][3]; int iPlateType; int iChannelDataType;
    int nChannels; char szChannelNames[MAX_ANALOG_CHANNELS][MAX_NAMELENGTH];
} sForcePlateDescription;
typedef struct {
    int type;
    union {
        sMarkerSetDescription *MarkerSetDescription; sRigidBodyDescription *RigidBodyDescription;
        sSkeletonDescription *SkeletonDescription; sForcePlateDescription *ForcePlateDescription;
        sMarkerSetData *MarkerSetData;
    } Data;
} sDataDescription;
typedef struct { int nDataDescriptions; sDataDescription arrDataDescriptions[MAX_MODELS]; } sDataDescriptions;
typedef struct {
    int iFrame; int nMarkerSets; sMarkerSetData MocapData[MAX_MODELS]; int nOtherMarkers; MarkerData *OtherMarkers;
    int nRigidBodies; sRigidBodyData RigidBodies[MAX_RIGIDBODIES]; int nSkeletons; sSkeletonData Skeletons[MAX_SKELETONS];
    int nLabeledMarkers; sMarker LabeledMarkers[MAX_LABELED_MARKERS]; int nAnalogdatas;
    float Analogdata[MAX_ANALOG_CHANNELS]; float fLatency; unsigned int Timecode; unsigned int TimecodeSubframe;
    long long iTimeStamp; short params;
} sFrameOfMocapData;
typedef enum { RigidBodyChange = 1, SkeletonChange } NotifyType;
typedef enum { ActionAdd = 1, ActionRemove, ActionCover } NotifyAction;
typedef struct {
    NotifyType nType; NotifyAction nValue; int nParam1; int nParam2; int nParam3; int nParam4;
    unsigned long long nTimeStamp; char sMsg[MAX_MSG_LENGTH];
} sNotifyMsg;

typedef void (*DataCallback)(sFrameOfMocapData *, void *);
typedef void (*NotifyCallback)(sNotifyMsg *, void *);

/* ---- scenario (test control) ------------------------------------------------------------------ */
static int g_frames = 300, g_rate_hz = 200, g_appear_at = 50, g_lost_from = 120, g_lost_to = 140;
static int g_gap_at = 200, g_gap = 3, g_first_frame = 1000;
static long long g_ts_unit_ns = 1000; /* iTimeStamp unit: microseconds by default */
static float g_latency_s = 0.004f;
static char g_server[64] = "10.1.1.198";
#define TRUTH_MAX 100000
static long long g_truth_capture_ns[TRUTH_MAX];
static volatile int g_emitted = 0;
static int g_steady = 0;

static void apply_env(void) {
    const char *frames = getenv("FAKE_NOKOV_FRAMES");
    if (frames && atoi(frames) > 0) g_frames = atoi(frames) < TRUTH_MAX ? atoi(frames) : TRUTH_MAX;
    const char *rate = getenv("FAKE_NOKOV_RATE_HZ");
    if (rate && atoi(rate) > 0) g_rate_hz = atoi(rate);
    const char *steady = getenv("FAKE_NOKOV_STEADY");
    if (steady && strcmp(steady, "1") == 0) { g_steady = 1; g_lost_from = g_lost_to = -1; g_gap = 0; }
}

API void FakeNokov_Configure(int frames, int rate_hz, int appear_at, int lost_from, int lost_to, int gap_at, int gap,
                             long long ts_unit_ns, float latency_s, const char *server) {
    g_frames = frames < TRUTH_MAX ? frames : TRUTH_MAX; g_rate_hz = rate_hz; g_appear_at = appear_at;
    g_lost_from = lost_from; g_lost_to = lost_to; g_gap_at = gap_at; g_gap = gap; g_ts_unit_ns = ts_unit_ns;
    g_latency_s = latency_s;
    strncpy(g_server, server, sizeof(g_server) - 1);
}
API int FakeNokov_Emitted(void) { return g_emitted; }
API long long FakeNokov_TruthCaptureNs(int k) { return (k >= 0 && k < TRUTH_MAX) ? g_truth_capture_ns[k] : -1; }
/* Frame number of frame index k (the gap shifts all later numbers). */
API int FakeNokov_FrameNumber(int k) { return g_first_frame + k + (k >= g_gap_at ? g_gap : 0); }
API void FakeNokov_BodyPositionMm(int id, int k, double out[3]) {
    if (id == 1) { out[0] = 100.0 + 0.5 * k; out[1] = -200.0; out[2] = 300.25; }
    else { out[0] = 500.0; out[1] = 600.0 + 1.0 * k; out[2] = -700.5; }
}

/* ---- client ------------------------------------------------------------------------------------ */
typedef struct {
    DataCallback data_cb; void *data_user; NotifyCallback notify_cb; void *notify_user;
    pthread_t thread; volatile int running; int initialized;
    sDataDescriptions desc; sRigidBodyDescription rbdesc[2];
    sFrameOfMocapData frame;
    pthread_mutex_t lock;
} Client;

static long long now_ns(clockid_t c) {
    struct timespec ts; clock_gettime(c, &ts); return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static void add_rb_desc(Client *c, int idx, int id, const char *name) {
    sRigidBodyDescription *d = &c->rbdesc[idx];
    memset(d, 0, sizeof(*d));
    strncpy(d->szName, name, MAX_NAMELENGTH - 1); d->ID = id; d->parentID = -1; d->qw = 1.0f;
    pthread_mutex_lock(&c->lock);
    c->desc.arrDataDescriptions[idx].type = 1; /* Descriptor_RigidBody */
    c->desc.arrDataDescriptions[idx].Data.RigidBodyDescription = d;
    c->desc.nDataDescriptions = idx + 1;
    pthread_mutex_unlock(&c->lock);
}

static void fill_body(sRigidBodyData *rb, int id, int k, bool lost) {
    memset(rb, 0, sizeof(*rb));
    if (g_steady) k = 0;
    double p[3]; FakeNokov_BodyPositionMm(id, k, p);
    double a = 0.01 * k * (id == 1 ? 1.0 : -2.0);
    rb->ID = id;
    if (lost) {
        rb->x = rb->y = rb->z = (float)UNDEFINED; rb->qx = rb->qy = rb->qz = rb->qw = 0.0f; rb->params = 0;
        rb->nMarkers = 0; rb->MeanError = 0.0f;
    } else {
        rb->x = (float)p[0]; rb->y = (float)p[1]; rb->z = (float)p[2];
        rb->qx = 0.0f; rb->qy = 0.0f; rb->qz = (float)sin(a / 2); rb->qw = (float)cos(a / 2);
        rb->params = 1; rb->nMarkers = 4; rb->MeanError = 0.25f;
    }
}

static void *player(void *arg) {
    Client *c = (Client *)arg;
    long long period = 1000000000LL / g_rate_hz;
    const char *start_file = getenv("FAKE_NOKOV_START_FILE");
    while (start_file && c->running && access(start_file, F_OK) != 0) usleep(10000);
    long long t0 = now_ns(CLOCK_MONOTONIC);
    for (int k = 0; k < g_frames && c->running; k++) {
        long long due = t0 + (k + 1) * period;
        struct timespec ts = {due / 1000000000LL, due % 1000000000LL};
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
        if (k == g_appear_at) {
            add_rb_desc(c, 1, 2, "tool");
            if (c->notify_cb) {
                sNotifyMsg m; memset(&m, 0, sizeof(m));
                m.nType = RigidBodyChange; m.nValue = ActionAdd; m.nParam1 = 2;
                m.nTimeStamp = (unsigned long long)(now_ns(CLOCK_REALTIME) / 1000000LL);
                strcpy(m.sMsg, "rigid body added");
                c->notify_cb(&m, c->notify_user);
            }
        }
        sFrameOfMocapData *f = &c->frame;
        f->iFrame = FakeNokov_FrameNumber(k);
        f->nRigidBodies = 0;
        fill_body(&f->RigidBodies[f->nRigidBodies++], 1, k, false);
        if (k >= g_appear_at) fill_body(&f->RigidBodies[f->nRigidBodies++], 2, k, k >= g_lost_from && k < g_lost_to);
        f->fLatency = g_latency_s;
        long long lat_ns = (long long)llround((double)g_latency_s * 1e9);
        /* The frame is "sent" now; it was captured latency earlier. */
        long long send_rt = now_ns(CLOCK_REALTIME), send_mono = now_ns(CLOCK_MONOTONIC);
        g_truth_capture_ns[k] = send_rt - lat_ns;
        f->iTimeStamp = (send_mono - lat_ns) / g_ts_unit_ns;
        f->params = 0;
        DataCallback cb = c->data_cb;
        if (cb) cb(f, c->data_user);
        g_emitted = k + 1;
    }
    return NULL;
}

API int CreateClient(void **out) {
    Client *c = (Client *)calloc(1, sizeof(Client));
    if (!c) return 1;
    pthread_mutex_init(&c->lock, NULL);
    add_rb_desc(c, 0, 1, "base");
    *out = c;
    return 0;
}
API void NokovVersion(void *h, unsigned char v[4]) { (void)h; v[0] = 2; v[1] = 5; v[2] = 53; v[3] = 12; }
API int SetDataCallback(void *h, DataCallback cb, void *user) {
    Client *c = (Client *)h; c->data_cb = cb; c->data_user = user; return 0;
}
API int SetNotifyMsgCallback(void *h, NotifyCallback cb, void *user) {
    Client *c = (Client *)h; c->notify_cb = cb; c->notify_user = user; return 0;
}
API int Initialize(void *h, const char *ip) {
    Client *c = (Client *)h;
    if (!ip || strcmp(ip, g_server) != 0) { usleep(20000); return 3; } /* ErrorCode_Network */
    if (c->initialized) return 0;
    apply_env();
    c->running = 1; c->initialized = 1;
    g_emitted = 0;
    return pthread_create(&c->thread, NULL, player, c) == 0 ? 0 : 1;
}
API int Uninitialize(void *h) {
    Client *c = (Client *)h;
    if (c->initialized) { c->running = 0; pthread_join(c->thread, NULL); c->initialized = 0; }
    return 0;
}
API int GetDataDescriptions(void *h, sDataDescriptions **out) {
    Client *c = (Client *)h;
    pthread_mutex_lock(&c->lock);
    *out = &c->desc; /* owned by the client, like a cached description block */
    pthread_mutex_unlock(&c->lock);
    return 0;
}
API int DestroyClient(void *h) {
    Client *c = (Client *)h; Uninitialize(h); pthread_mutex_destroy(&c->lock); free(c); return 0;
}

/* Layout probe: sizes and a few offsets, compared with the ctypes declarations by the tests. */
#include <stddef.h>
API long FakeNokov_Layout(const char *what) {
#define L(n, v) if (strcmp(what, n) == 0) return (long)(v)
    L("sMarker", sizeof(sMarker)); L("sMarkerSetData", sizeof(sMarkerSetData));
    L("sRigidBodyDescription", sizeof(sRigidBodyDescription)); L("sRigidBodyData", sizeof(sRigidBodyData));
    L("sSkeletonData", sizeof(sSkeletonData)); L("sSkeletonDescription", sizeof(sSkeletonDescription));
    L("sForcePlateDescription", sizeof(sForcePlateDescription)); L("sDataDescription", sizeof(sDataDescription));
    L("sDataDescriptions", sizeof(sDataDescriptions)); L("sFrameOfMocapData", sizeof(sFrameOfMocapData));
    L("sNotifyMsg", sizeof(sNotifyMsg));
    L("sFrameOfMocapData.nRigidBodies", offsetof(sFrameOfMocapData, nRigidBodies));
    L("sFrameOfMocapData.RigidBodies", offsetof(sFrameOfMocapData, RigidBodies));
    L("sFrameOfMocapData.fLatency", offsetof(sFrameOfMocapData, fLatency));
    L("sFrameOfMocapData.iTimeStamp", offsetof(sFrameOfMocapData, iTimeStamp));
    L("sFrameOfMocapData.params", offsetof(sFrameOfMocapData, params));
    L("sRigidBodyData.MeanError", offsetof(sRigidBodyData, MeanError));
    L("sRigidBodyData.params", offsetof(sRigidBodyData, params));
    L("sNotifyMsg.nTimeStamp", offsetof(sNotifyMsg, nTimeStamp));
#undef L
    return -1;
}

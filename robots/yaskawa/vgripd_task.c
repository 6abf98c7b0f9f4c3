/* vgripd robot socket server for Yaskawa controllers, a MotoPlus application (needs the
 * MotoPlus SDK and its runtime option on the controller; INFORM has no socket instructions).
 * @@GENERATED@@
 *
 * The controller is the server here: vg_accept_task listens on VG_PORT and vgripd's
 * robot_socket link (mode = "client") dials in. The INFORM job VGLOCATE asks for a locate
 * (VGNEXT: the next object of its pick list) through variables: I050 = 1 request, I051 = 1
 * done, I052 recipe, I053 status, I054 = 1 next instead of locate, D050 job id, D051 warnings,
 * D052..D057 the offset @@FIELDS@@ (@@CONVENTION@@) in position-variable units (0.001 mm,
 * 0.0001 deg; so VG_SCALE must be at least 10000), base frame, D058 pick-list objects after
 * this one. Frames: docs/robot_socket.md.
 *
 * Walked hand-eye calibration (VGWALK.JBI; docs/calibration-handeye.md): I054 = 2 asks for
 * the next target, I054 = 3 sends CAPTURE_AT with the flange pose the task reads (tool 0 at
 * the flange, base frame); either way a target without joint values (mpConvCartPosToAxes)
 * is skipped (NEXT with recipe 1) and the next one is left in D052..D057. Tool file 0 must be
 * all 0 (the flange), as the tool VGWALK moves with: a pose read more than VG_AT_TOL_UM /
 * VG_AT_TOL_DEG4 off the target the job moved to is not sent, the step answers -2.
 *
 * A conveyor (docs/robots/yaskawa.md, "Conveyor"): I054 = 4 a locate with the count latched at
 * the image in D059 (VGBLOC); I054 = 5 the intercept's requests: the next part at the count
 * now, predicted D059 counts ahead (VGCATCH); I054 = 6 waits until the count reaches D061;
 * I054 = 7 the next part at the count now (for a tracking option). The encoder count now is
 * D060 (vgEncoderNow: change it to your wiring). A counted request's BELT frame leaves D061
 * the count the offset belongs to, D062 ALONG and D063 ACROSS (0.001 mm), D064 THETA
 * (0.0001 deg), D065 the parts queued, D066 the latch source.
 */
#include "motoPlus.h"

#define VG_PORT @@PORT@@
#define VG_SCALE @@SCALE@@
#define VG_TIMEOUT_MS @@TIMEOUT_MS@@
#define VG_BUSY_WAIT_MS @@BUSY_WAIT_MS@@
#define VG_BUSY_TRIES @@BUSY_TRIES@@
#define VG_ATTEMPTS @@ATTEMPTS@@
#define VG_LOCATE @@LOCATE@@
#define VG_NEXT @@NEXT@@
#define VG_CAPTURED @@CAPTURED@@
#define VG_RESULT @@RESULT@@
#define VG_REFUSED @@REFUSED@@
#define VG_CAPTURE_AT @@CAPTURE_AT@@ /* a locate with the flange pose reached (VGWALK) */
#define VG_AT_BYTES @@AT_BYTES@@ /* its length: 16 + 7 pose words */
/* A conveyor: the counted requests (24 bytes: the encoder count and a frame id), BELT */
#define VG_LOCATE_AT @@LOCATE_AT@@
#define VG_NEXT_AT @@NEXT_AT@@
#define VG_PREDICT @@PREDICT@@
#define VG_BELT @@BELT@@
#define VG_COUNTED_BYTES @@COUNTED_BYTES@@
#define VG_WALK_SPEED_MM_S @@WALK_SPEED_V@@ /* VGWALK.JBI's MOVL V= ([calibration_walk]) */
#define VG_WALK_SETTLE_S @@WALK_SETTLE_T@@ /* VGWALK.JBI's TIMER T= before CAPTURE_AT */
#define VG_AT_TOL_UM 1000 /* the flange pose read at a target: within 1 mm ... */
#define VG_AT_TOL_DEG4 1000 /* ... and 0.1 deg per angle of it, else the walk pauses (-2) */
#define VG_VAR 50 /* I050.., D050.. */
#define VG_TICK_MS 4 /* one mpTaskDelay tick: the controller's interpolation period */

static int vgClient = -1;
static LONG vgId = 0;
static LONG vgW[16];
static LONG vgCount = 0; /* the count a counted request sends */

static LONG vgGet(USHORT vgType, USHORT vgIndex)
{
    MP_VAR_INFO vgInfo;
    LONG vgValue = 0;
    vgInfo.usType = vgType;
    vgInfo.usIndex = vgIndex;
    mpGetVarData(&vgInfo, &vgValue, 1);
    return vgValue;
}

static void vgPut(USHORT vgType, USHORT vgIndex, LONG vgValue)
{
    MP_VAR_DATA vgData;
    vgData.usType = vgType;
    vgData.usIndex = vgIndex;
    vgData.ulValue = vgValue;
    mpPutVarData(&vgData, 1);
}

/* Drop the connection after a failure; vgripd dials in again (back-off). */
static void vgDrop(void)
{
    if (vgClient >= 0) {
        mpClose(vgClient);
        vgClient = -1;
    }
}

/* The belt's encoder count now: D060, kept current by the cell (the PLC over the fieldbus,
 * or an encoder card): change this to your wiring. */
static LONG vgEncoderNow(void)
{
    return vgGet(MP_RESTYPE_VAR_D, VG_VAR + 10);
}

/* 1 once the count vgNow has reached vgN; the difference wraps with the 32-bit counter. */
static int vgReached(LONG vgNow, LONG vgN)
{
    return (unsigned int)vgNow - (unsigned int)vgN <= 2147483647;
}

/* The robot's joint angles now; 0 when read. */
static int vgAngles(LONG *vgAngle)
{
    MP_CTRL_GRP_SEND_DATA vgGrp;
    MP_PULSE_POS_RSP_DATA vgPulse;
    memset(&vgGrp, 0, sizeof(vgGrp));
    vgGrp.sCtrlGrp = 0;
    if (mpGetPulsePos(&vgGrp, &vgPulse) != 0) {
        return -1;
    }
    return mpConvPulseToAngle(0, vgPulse.lPos, vgAngle);
}

/* The flange pose now (tool 0, base frame) in position-variable units; 0 when read. */
static int vgFlange(MP_COORD *vgCoord)
{
    LONG vgAngle[MP_GRP_AXES_NUM];
    UINT vgFig;
    if (vgAngles(vgAngle) != 0) {
        return -1;
    }
    return mpConvAxesToCartPos(0, vgAngle, 0, &vgFig, vgCoord);
}

/* 1 when the target in D052..D057 has joint values within the limits (tool 0), else 0. */
static int vgReachable(void)
{
    MP_COORD vgCoord;
    LONG vgNow[MP_GRP_AXES_NUM], vgAngle[MP_GRP_AXES_NUM];
    UINT vgFig;
    if (vgAngles(vgNow) != 0 || mpConvAxesToCartPos(0, vgNow, 0, &vgFig, &vgCoord) != 0) {
        return 0;
    }
    vgCoord.x = vgGet(MP_RESTYPE_VAR_D, VG_VAR + 2);
    vgCoord.y = vgGet(MP_RESTYPE_VAR_D, VG_VAR + 3);
    vgCoord.z = vgGet(MP_RESTYPE_VAR_D, VG_VAR + 4);
    vgCoord.rx = vgGet(MP_RESTYPE_VAR_D, VG_VAR + 5);
    vgCoord.ry = vgGet(MP_RESTYPE_VAR_D, VG_VAR + 6);
    vgCoord.rz = vgGet(MP_RESTYPE_VAR_D, VG_VAR + 7);
    return mpConvCartPosToAxes(0, &vgCoord, 0, vgFig, vgNow, MP_KINEMA_FIG, vgAngle) == 0;
}

/* 1 when the flange pose read (tool file 0) is the target in D052..D057 that VGWALK moved to
 * (with the tool selected on the pendant): both tools are the flange only then. */
static int vgAtTarget(const MP_COORD *vgCoord)
{
    LONG vgRead[6], vgD;
    int vgI;
    vgRead[0] = vgCoord->x;
    vgRead[1] = vgCoord->y;
    vgRead[2] = vgCoord->z;
    vgRead[3] = vgCoord->rx;
    vgRead[4] = vgCoord->ry;
    vgRead[5] = vgCoord->rz;
    for (vgI = 0; vgI < 6; vgI++) {
        vgD = vgRead[vgI] - vgGet(MP_RESTYPE_VAR_D, VG_VAR + 2 + vgI);
        if (vgI >= 3) { /* 0.0001 deg, wrapped to -180 .. 180 deg */
            vgD = (vgD % 3600000 + 5400000) % 3600000 - 1800000;
        }
        if (vgD > (vgI < 3 ? VG_AT_TOL_UM : VG_AT_TOL_DEG4)
                || -vgD > (vgI < 3 ? VG_AT_TOL_UM : VG_AT_TOL_DEG4)) {
            return 0;
        }
    }
    return 1;
}

/* One request (VG_LOCATE, VG_NEXT, VG_CAPTURE_AT with the 7 pose words vgAt, or a counted
 * one with vgCount): the status of its final answer, or -1 when none came in time. */
static LONG vgRequest(LONG vgCmd, LONG vgRecipe, const LONG *vgAt)
{
    LONG vgReq[11];
    int vgGot, vgN, vgI, vgLen = 16, vgWaited = 0;
    while (vgClient < 0) {
        if (vgWaited >= VG_TIMEOUT_MS) {
            return -1;
        }
        mpTaskDelay(1);
        vgWaited += VG_TICK_MS;
    }
    vgReq[0] = mpHtonl(vgCmd);
    vgReq[1] = mpHtonl(vgId);
    vgReq[2] = mpHtonl(vgRecipe);
    vgReq[3] = 0;
    if (vgCmd == VG_CAPTURE_AT) {
        for (vgI = 0; vgI < 7; vgI++) {
            vgReq[4 + vgI] = mpHtonl(vgAt[vgI]);
        }
        vgLen = VG_AT_BYTES;
    }
    if (vgCmd == VG_LOCATE_AT || vgCmd == VG_NEXT_AT || vgCmd == VG_PREDICT) {
        vgReq[4] = mpHtonl(vgCount);
        vgReq[5] = 0; /* the frame id */
        vgLen = VG_COUNTED_BYTES;
    }
    if (mpSend(vgClient, (char *)vgReq, vgLen, 0) != vgLen) {
        return -1;
    }
    for (;;) {
        for (vgGot = 0; vgGot < 64; vgGot += vgN) {
            /* each mpRecv waits at most VG_TIMEOUT_MS (SO_RCVTIMEO, set at accept) */
            vgN = mpRecv(vgClient, (char *)vgW + vgGot, 64 - vgGot, 0);
            if (vgN <= 0) {
                return -1;
            }
        }
        for (vgI = 0; vgI < 16; vgI++) {
            vgW[vgI] = mpNtohl(vgW[vgI]);
        }
        if (vgW[0] != VG_CAPTURED && vgW[0] != VG_RESULT && vgW[0] != VG_REFUSED
                && vgW[0] != VG_BELT) {
            return -1; /* not a vgripd answer: the stream is out of step */
        }
        if (vgW[1] == vgId && vgW[0] == VG_BELT) {
            vgPut(MP_RESTYPE_VAR_D, VG_VAR + 11, vgW[2]); /* the count the offset belongs to */
            vgPut(MP_RESTYPE_VAR_D, VG_VAR + 12, vgW[5] / (VG_SCALE / 1000));
            vgPut(MP_RESTYPE_VAR_D, VG_VAR + 13, vgW[6] / (VG_SCALE / 1000));
            vgPut(MP_RESTYPE_VAR_D, VG_VAR + 14, vgW[7] / (VG_SCALE / 10000));
            vgPut(MP_RESTYPE_VAR_D, VG_VAR + 15, vgW[8]);
            vgPut(MP_RESTYPE_VAR_D, VG_VAR + 16, vgW[3]);
            continue;
        }
        if (vgW[1] == vgId && vgW[0] != VG_CAPTURED) {
            vgPut(MP_RESTYPE_VAR_D, VG_VAR, vgW[3]);
            vgPut(MP_RESTYPE_VAR_D, VG_VAR + 1, vgW[4]);
            vgPut(MP_RESTYPE_VAR_D, VG_VAR + 8, vgW[15]);
            if (vgW[5] == 6) {
                if (vgW[14] != VG_SCALE) {
                    return -2; /* vgripd sends another scale: generate the program again */
                }
                for (vgI = 0; vgI < 3; vgI++) { /* mm x scale -> 0.001 mm */
                    vgPut(MP_RESTYPE_VAR_D, VG_VAR + 2 + vgI, vgW[6 + vgI] / (VG_SCALE / 1000));
                }
                for (vgI = 3; vgI < 6; vgI++) { /* deg x scale -> 0.0001 deg */
                    vgPut(MP_RESTYPE_VAR_D, VG_VAR + 2 + vgI, vgW[6 + vgI] / (VG_SCALE / 10000));
                }
            }
            return vgW[2];
        }
    }
}

/* One request with retries: asks again after BUSY (40), gives up (-1) after VG_ATTEMPTS
 * requests in a row without an answer. */
static LONG vgAsk(LONG vgCmd, LONG vgRecipe, const LONG *vgAt)
{
    LONG vgStatus;
    int vgUnanswered = 0, vgBusy = 0;
    for (;;) {
        vgId = vgId >= 2147483646 ? 1 : vgId + 1;
        vgStatus = vgRequest(vgCmd, vgRecipe, vgAt);
        if (vgStatus == -2) {
            return -1;
        }
        if (vgStatus == -1) {
            vgDrop();
            if (++vgUnanswered >= VG_ATTEMPTS) {
                return -1;
            }
        } else if (vgStatus == 40 && vgBusy < VG_BUSY_TRIES) {
            vgBusy++;
            mpTaskDelay(VG_BUSY_WAIT_MS / VG_TICK_MS);
        } else {
            return vgStatus;
        }
    }
}

/* The walk's step (I054 = 2: next target, 3: CAPTURE_AT here): the status, a reachable next
 * target in D052..D057 for 1 or 2 (unreachable ones are skipped with NEXT, recipe 1). */
static LONG vgWalkStep(LONG vgMode)
{
    MP_COORD vgCoord;
    LONG vgAt[7];
    LONG vgStatus;
    if (vgMode == 3) {
        if (vgFlange(&vgCoord) != 0) {
            return -1;
        }
        if (!vgAtTarget(&vgCoord)) {
            return -2; /* tool file 0 or the selected tool is not the flange */
        }
        vgAt[0] = vgCoord.x * (VG_SCALE / 1000); /* 0.001 mm -> mm x scale */
        vgAt[1] = vgCoord.y * (VG_SCALE / 1000);
        vgAt[2] = vgCoord.z * (VG_SCALE / 1000);
        vgAt[3] = vgCoord.rx * (VG_SCALE / 10000); /* 0.0001 deg -> deg x scale */
        vgAt[4] = vgCoord.ry * (VG_SCALE / 10000);
        vgAt[5] = vgCoord.rz * (VG_SCALE / 10000);
        vgAt[6] = 0;
        vgStatus = vgAsk(VG_CAPTURE_AT, 0, vgAt);
    } else {
        vgStatus = vgAsk(VG_NEXT, 0, 0);
    }
    while ((vgStatus == 1 || vgStatus == 2) && !vgReachable()) {
        vgStatus = vgAsk(VG_NEXT, 1, 0); /* not reachable: skipped (recipe 1) */
    }
    return vgStatus;
}

/* The conveyor's steps (I054 = 4 .. 7, see the head of this file): the status. */
static LONG vgBeltStep(LONG vgMode)
{
    LONG vgStatus;
    if (vgMode == 4) {
        vgCount = vgGet(MP_RESTYPE_VAR_D, VG_VAR + 9);
        return vgAsk(VG_LOCATE_AT, vgGet(MP_RESTYPE_VAR_I, VG_VAR + 2), 0);
    }
    if (vgMode == 6) { /* the part reaches the gripper: the status stays the PREDICT's */
        while (!vgReached(vgEncoderNow(), vgGet(MP_RESTYPE_VAR_D, VG_VAR + 11))) {
            mpTaskDelay(1);
        }
        return vgGet(MP_RESTYPE_VAR_I, VG_VAR + 3);
    }
    vgCount = vgEncoderNow();
    vgStatus = vgAsk(VG_NEXT_AT, 0, 0);
    if (vgMode == 7 || (vgStatus != 1 && vgStatus != 2)) {
        return vgStatus;
    }
    /* the intercept: where the part will be D059 counts from now (D061 = that count) */
    vgCount = (LONG)((unsigned int)vgEncoderNow() + (unsigned int)vgGet(MP_RESTYPE_VAR_D, VG_VAR + 9));
    return vgAsk(VG_PREDICT, 0, 0);
}

/* Serves the INFORM jobs: I050 = 1 starts a locate (I054 = 1: a next; 2, 3: the walk's
 * steps; 4 .. 7: the conveyor's), I051 = 1 says it is done. */
static void vg_job_task(void)
{
    LONG vgMode;
    for (;;) {
        if (vgGet(MP_RESTYPE_VAR_I, VG_VAR) == 1 && vgGet(MP_RESTYPE_VAR_I, VG_VAR + 1) == 0) {
            vgMode = vgGet(MP_RESTYPE_VAR_I, VG_VAR + 4);
            if (vgMode == 1) {
                vgPut(MP_RESTYPE_VAR_I, VG_VAR + 3, vgAsk(VG_NEXT, 0, 0));
            } else if (vgMode == 2 || vgMode == 3) {
                vgPut(MP_RESTYPE_VAR_I, VG_VAR + 3, vgWalkStep(vgMode));
            } else if (vgMode >= 4 && vgMode <= 7) {
                vgPut(MP_RESTYPE_VAR_I, VG_VAR + 3, vgBeltStep(vgMode));
            } else {
                vgPut(MP_RESTYPE_VAR_I, VG_VAR + 3,
                      vgAsk(VG_LOCATE, vgGet(MP_RESTYPE_VAR_I, VG_VAR + 2), 0));
            }
            vgPut(MP_RESTYPE_VAR_I, VG_VAR + 1, 1);
        }
        mpTaskDelay(2);
    }
}

/* Accepts vgripd's connection; a new one replaces the old (vgripd reconnected). */
static void vg_accept_task(void)
{
    struct sockaddr_in vgAddr;
    struct timeval vgTimeout;
    int vgListener, vgNew, vgLen;
    vgListener = mpSocket(AF_INET, SOCK_STREAM, 0);
    memset(&vgAddr, 0, sizeof(vgAddr));
    vgAddr.sin_family = AF_INET;
    vgAddr.sin_addr.s_addr = mpHtonl(INADDR_ANY);
    vgAddr.sin_port = mpHtons(VG_PORT);
    mpBind(vgListener, (struct sockaddr *)&vgAddr, sizeof(vgAddr));
    mpListen(vgListener, 1);
    vgTimeout.tv_sec = VG_TIMEOUT_MS / 1000;
    vgTimeout.tv_usec = (VG_TIMEOUT_MS % 1000) * 1000;
    for (;;) {
        vgLen = sizeof(vgAddr);
        vgNew = mpAccept(vgListener, (struct sockaddr *)&vgAddr, &vgLen);
        if (vgNew < 0) {
            mpTaskDelay(100);
            continue;
        }
        mpSetsockopt(vgNew, SOL_SOCKET, SO_RCVTIMEO, (char *)&vgTimeout, sizeof(vgTimeout));
        vgDrop();
        vgClient = vgNew;
    }
}

void mpUsrRoot(int arg1, int arg2, int arg3, int arg4, int arg5,
               int arg6, int arg7, int arg8, int arg9, int arg10)
{
    mpCreateTask(MP_PRI_TIME_NORMAL, MP_STACK_SIZE, (FUNCPTR)vg_accept_task,
                 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
    mpCreateTask(MP_PRI_TIME_NORMAL, MP_STACK_SIZE, (FUNCPTR)vg_job_task,
                 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
    mpExitUsrRoot;
}

MODULE VgripdSocket
  ! vgripd robot socket client for ABB RAPID socket messaging (docs/robot_socket.md).
  ! @@GENERATED@@
  ! Use in a program:
  !   vgStatus := vgLocate(0);
  !   IF vgStatus = 1 OR vgStatus = 2 THEN
  !     ! the offset is in the base frame: it goes on the left of the taught grip
  !     MoveL PoseMult(vgOffset, pGrip) ...
  !   ENDIF
  ! A pallet (pick lists): vgStatus := vgLocate(0), then while vgStatus is 1 or 2 pick the
  ! object and ask vgStatus := vgNext() until it answers 10 (NOT_FOUND: all picked).
  ! Walked hand-eye calibration: vgWalk; (docs/robots/abb.md, "Walked hand-eye calibration").
  ! A conveyor (docs/robots/abb.md, "Conveyor"): vgLocateAt(0, count latched at the image),
  ! then vgIntercept lead, tGrip, v500, tGripper; and close the gripper on 1 or 2.
  CONST string VG_HOST := "@@HOST@@";
  CONST num VG_PORT := @@PORT@@;
  CONST num VG_SCALE := @@SCALE@@; ! 0: the answer's values are float32
  CONST num VG_TIMEOUT_S := @@TIMEOUT_S@@; ! for each answer frame
  CONST num VG_CONNECT_TIMEOUT_S := @@CONNECT_TIMEOUT_S@@;
  CONST num VG_BUSY_WAIT_S := @@BUSY_WAIT_S@@; ! pause before asking again after BUSY (40)
  CONST num VG_BUSY_TRIES := @@BUSY_TRIES@@;
  CONST num VG_ATTEMPTS := @@ATTEMPTS@@; ! unanswered requests in a row before Stop
  ! Frame word 0: "VG", version 1, command or answer kind.
  CONST dnum VG_LOCATE := @@LOCATE@@;
  CONST dnum VG_NEXT := @@NEXT@@;
  CONST dnum VG_CAPTURED := @@CAPTURED@@;
  CONST dnum VG_RESULT := @@RESULT@@;
  CONST dnum VG_REFUSED := @@REFUSED@@;
  CONST dnum VG_CAPTURE_AT := @@CAPTURE_AT@@; ! a locate with the flange pose reached (vgWalk)
  CONST num VG_AT_BYTES := @@AT_BYTES@@; ! its length: 16 + 7 pose words
  ! A conveyor: the counted requests (24 bytes: the encoder count and a frame id), the BELT frame
  CONST dnum VG_LOCATE_AT := @@LOCATE_AT@@;
  CONST dnum VG_NEXT_AT := @@NEXT_AT@@;
  CONST dnum VG_PREDICT := @@PREDICT@@;
  CONST dnum VG_BELT := @@BELT@@;
  CONST num VG_COUNTED_BYTES := @@COUNTED_BYTES@@;
  ! vgWalk (from [calibration_walk] of the config): linear speed, standstill before the image
  CONST num VG_WALK_SPEED_MM_S := @@WALK_SPEED_MM_S@@;
  CONST num VG_WALK_SETTLE_S := @@WALK_SETTLE_S@@;
  ! The last answer. vgOffset: @@FIELDS@@ (@@CONVENTION@@), base frame.
  PERS pose vgOffset := [[0,0,0],[1,0,0,0]];
  VAR num vgStatus := 0;
  VAR dnum vgJob := 0;
  VAR num vgWarnings := 0;
  VAR num vgRemaining := 0; ! pick lists: objects after this one
  VAR bool vgCaptured := FALSE;
  ! The BELT frame of the last counted request: the count vgOffset belongs to, the latch, the
  ! part in belt terms (mm, deg) and the parts still queued
  VAR dnum vgBeltCount := 0;
  VAR num vgBeltSource := 0;
  VAR num vgLatchErr := 0;
  VAR num vgAlong := 0;
  VAR num vgAcross := 0;
  VAR num vgTheta := 0;
  VAR num vgQueued := 0;
  VAR dnum vgCount := 0; ! the count a counted request sends
  VAR dnum vgId := 0;
  VAR bool vgConnected := FALSE;
  VAR socketdev vgSocket;
  VAR rawbytes vgRaw;
  VAR num vgAt{7}; ! the flange pose CAPTURE_AT sends: x, y, z mm, q1..q4

  ! Ask vgripd for the offset and return the status; 1 or 2: vgOffset is set.
  FUNC num vgLocate(num vgRecipe)
    RETURN vgAsk(VG_LOCATE, vgRecipe);
  ENDFUNC

  ! The next object of the last vgLocate's pick list (no new image); 10: none left.
  FUNC num vgNext()
    RETURN vgAsk(VG_NEXT, 0);
  ENDFUNC

  ! A locate on a conveyor recipe: vgLatched is the encoder count latched at the exposure.
  FUNC num vgLocateAt(num vgRecipe, dnum vgLatched)
    vgCount := vgLatched;
    RETURN vgAsk(VG_LOCATE_AT, vgRecipe);
  ENDFUNC

  ! The conveyor's next part (most downstream in the window at count vgNow), its offset at its
  ! own latched count vgBeltCount: what a tracking option takes with that count.
  FUNC num vgNextAt(dnum vgNow)
    vgCount := vgNow;
    RETURN vgAsk(VG_NEXT_AT, 0);
  ENDFUNC

  ! Where the part vgNextAt served will be at count vgN (vgOffset; 21: past the window).
  FUNC num vgPredict(dnum vgN)
    vgCount := vgN;
    RETURN vgAsk(VG_PREDICT, 0);
  ENDFUNC

  ! The belt's encoder count now: the 32-bit group input vgEncoder (the PLC or encoder card
  ! mapped there in the I/O configuration; change this function to your wiring).
  FUNC dnum vgEncoderNow()
    RETURN GInputDnum(vgEncoder);
  ENDFUNC

  ! TRUE once the count vgNow has reached vgN; the difference wraps with the 32-bit counter.
  FUNC bool vgReached(dnum vgNow, dnum vgN)
    VAR dnum vgD;
    vgD := vgNow - vgN;
    IF vgD < 0 THEN
      vgD := vgD + 4294967296;
    ENDIF
    RETURN vgD < 2147483648;
  ENDFUNC

  ! Without a tracking option: the next part, predicted vgLead counts ahead, the grip moved
  ! there (PoseMult(vgOffset, vgGrip) with vgTool, base frame), then waits until the encoder
  ! reaches that count. vgStatus 1 or 2: the part is under the gripper (close it at once);
  ! else the status, unmoved.
  PROC vgIntercept(dnum vgLead, robtarget vgGrip, speeddata vgSpeed, PERS tooldata vgTool)
    VAR dnum vgN;
    VAR pose vgP;
    VAR robtarget vgTarget;
    vgStatus := vgNextAt(vgEncoderNow());
    IF vgStatus <> 1 AND vgStatus <> 2 THEN
      RETURN;
    ENDIF
    vgN := vgEncoderNow() + vgLead;
    IF vgN >= 4294967296 THEN
      vgN := vgN - 4294967296;
    ENDIF
    vgStatus := vgPredict(vgN);
    IF vgStatus <> 1 AND vgStatus <> 2 THEN
      RETURN;
    ENDIF
    vgP := PoseMult(vgOffset, [vgGrip.trans, vgGrip.rot]);
    vgTarget := vgGrip;
    vgTarget.trans := vgP.trans;
    vgTarget.rot := vgP.rot;
    MoveL vgTarget, vgSpeed, fine, vgTool \WObj:=wobj0;
    WHILE NOT vgReached(vgEncoderNow(), vgN) DO
      WaitTime 0.004;
    ENDWHILE
  ENDPROC

  ! Walked hand-eye calibration (docs/calibration-handeye.md, "Walked calibration"): vgripd
  ! hands out the plan's targets (absolute flange poses in the robot's base frame), this
  ! routine moves. NEXT asks for a target, or skips one CalcJointT finds no solution for; at a
  ! target, after VG_WALK_SETTLE_S of standstill, CAPTURE_AT sends the flange pose reached
  ! (CRobT with tool0 in wobj0) and vgripd takes the image. 10 (NOT_FOUND): the walk is
  ! complete; any other status but 1 or 2 stops it. Dry-run the plan and check every target
  ! for collisions first; the speed is VG_WALK_SPEED_MM_S.
  PROC vgWalk()
    VAR robtarget vgGoal;
    VAR robtarget vgHere;
    VAR speeddata vgSpeed;
    vgSpeed := v50;
    vgSpeed.v_tcp := VG_WALK_SPEED_MM_S;
    vgStatus := vgAsk(VG_NEXT, 0);
    WHILE vgStatus = 1 OR vgStatus = 2 DO
      vgGoal := CRobT(\Tool:=tool0 \WObj:=wobj0); ! the present configuration
      vgGoal.trans := vgOffset.trans;
      vgGoal.rot := vgOffset.rot;
      IF vgReachable(vgGoal) THEN
        MoveL vgGoal, vgSpeed, fine, tool0 \WObj:=wobj0;
        WaitTime \InPos, VG_WALK_SETTLE_S;
        vgHere := CRobT(\Tool:=tool0 \WObj:=wobj0);
        vgAt{1} := vgHere.trans.x;
        vgAt{2} := vgHere.trans.y;
        vgAt{3} := vgHere.trans.z;
        vgAt{4} := vgHere.rot.q1;
        vgAt{5} := vgHere.rot.q2;
        vgAt{6} := vgHere.rot.q3;
        vgAt{7} := vgHere.rot.q4;
        vgStatus := vgAsk(VG_CAPTURE_AT, 0);
      ELSE
        vgStatus := vgAsk(VG_NEXT, 1); ! not reachable: skipped (recipe 1)
      ENDIF
    ENDWHILE
    IF vgStatus <> 10 THEN
      ErrWrite "vgripd", "hand-eye walk stopped: vgripd answered status " + NumToStr(vgStatus, 0);
      Stop;
    ENDIF
  ENDPROC

  ! TRUE when the robot has joint values for vgGoal (tool0, wobj0) within its limits.
  FUNC bool vgReachable(robtarget vgGoal)
    VAR jointtarget vgJoints;
    vgJoints := CalcJointT(vgGoal, tool0 \WObj:=wobj0);
    RETURN TRUE;
  ERROR
    IF ERRNO = ERR_ROBLIMIT OR ERRNO = ERR_OUTSIDE_REACH THEN
      RETURN FALSE;
    ENDIF
    RAISE;
  ENDFUNC

  ! One request with retries. After BUSY (40) it asks again every VG_BUSY_WAIT_S,
  ! VG_BUSY_TRIES times; it stops the program when VG_ATTEMPTS requests in a row got no
  ! answer (check the link with `vgripd status`).
  FUNC num vgAsk(dnum vgCmd, num vgRecipe)
    VAR num vgUnanswered := 0;
    VAR num vgBusy := 0;
    WHILE TRUE DO
      vgId := vgId + 1;
      IF vgId > 2147483646 THEN
        vgId := 1;
      ENDIF
      vgStatus := vgRequest(vgCmd, vgRecipe);
      IF vgStatus = -1 THEN
        vgClose;
        Incr vgUnanswered;
        IF vgUnanswered >= VG_ATTEMPTS THEN
          ErrWrite "vgripd", "no answer from vgripd at " + VG_HOST + ": is the link up?";
          Stop;
        ENDIF
      ELSEIF vgStatus = 40 AND vgBusy < VG_BUSY_TRIES THEN
        Incr vgBusy;
        WaitTime VG_BUSY_WAIT_S;
      ELSE
        RETURN vgStatus;
      ENDIF
    ENDWHILE
    RETURN -1;
  ENDFUNC

  ! One request (VG_LOCATE, VG_NEXT, VG_CAPTURE_AT with the pose in vgAt, or a counted one
  ! with vgCount): the status of its final answer, or -1 when none came in time; a counted
  ! request's BELT frame sets vgBeltCount .. vgQueued.
  FUNC num vgRequest(dnum vgCmd, num vgRecipe)
    VAR dnum vgWord;
    VAR dnum vgKind;
    VAR num vgCount;
    VAR num vgValue{7};
    IF NOT vgConnected THEN
      SocketCreate vgSocket;
      SocketConnect vgSocket, VG_HOST, VG_PORT \Time:=VG_CONNECT_TIMEOUT_S;
      vgConnected := TRUE;
    ENDIF
    vgCaptured := FALSE;
    ClearRawBytes vgRaw;
    PackRawBytes vgCmd, vgRaw \Network, 1 \IntX:=UDINT;
    PackRawBytes vgId, vgRaw \Network, 5 \IntX:=UDINT;
    PackRawBytes vgRecipe, vgRaw \Network, 9 \IntX:=UDINT;
    PackRawBytes 0, vgRaw \Network, 13 \IntX:=UDINT;
    IF vgCmd = VG_CAPTURE_AT THEN
      FOR vgI FROM 1 TO 7 DO
        PackRawBytes vgAt{vgI}, vgRaw \Network, 13 + 4 * vgI \Float4;
      ENDFOR
      SocketSend vgSocket \RawData:=vgRaw \NoOfBytes:=VG_AT_BYTES;
    ELSEIF vgCmd = VG_LOCATE_AT OR vgCmd = VG_NEXT_AT OR vgCmd = VG_PREDICT THEN
      PackRawBytes vgCount, vgRaw \Network, 17 \IntX:=UDINT;
      PackRawBytes 0, vgRaw \Network, 21 \IntX:=UDINT; ! the frame id: 0
      SocketSend vgSocket \RawData:=vgRaw \NoOfBytes:=VG_COUNTED_BYTES;
    ELSE
      SocketSend vgSocket \RawData:=vgRaw;
    ENDIF
    WHILE TRUE DO
      ClearRawBytes vgRaw;
      SocketReceive vgSocket \RawData:=vgRaw \ReadNoOfBytes:=64 \Time:=VG_TIMEOUT_S;
      UnpackRawBytes vgRaw \Network, 1, vgKind \IntX:=UDINT;
      IF vgKind <> VG_CAPTURED AND vgKind <> VG_RESULT AND vgKind <> VG_REFUSED AND vgKind <> VG_BELT THEN
        RETURN -1; ! not a vgripd answer: the stream is out of step
      ENDIF
      UnpackRawBytes vgRaw \Network, 5, vgWord \IntX:=UDINT;
      IF vgWord = vgId THEN
        IF vgKind = VG_CAPTURED THEN
          vgCaptured := TRUE; ! the images are taken: a robot-mounted camera may move on
        ELSEIF vgKind = VG_BELT THEN
          UnpackRawBytes vgRaw \Network, 9, vgBeltCount \IntX:=UDINT; ! vgOffset's count
          UnpackRawBytes vgRaw \Network, 13, vgBeltSource \IntX:=UDINT;
          UnpackRawBytes vgRaw \Network, 17, vgLatchErr \Float4;
          UnpackRawBytes vgRaw \Network, 21, vgAlong \Float4;
          UnpackRawBytes vgRaw \Network, 25, vgAcross \Float4;
          UnpackRawBytes vgRaw \Network, 29, vgTheta \Float4;
          UnpackRawBytes vgRaw \Network, 33, vgQueued \IntX:=UDINT;
        ELSE
          UnpackRawBytes vgRaw \Network, 13, vgJob \IntX:=UDINT;
          UnpackRawBytes vgRaw \Network, 17, vgWarnings \IntX:=UDINT;
          UnpackRawBytes vgRaw \Network, 21, vgCount \IntX:=UDINT;
          UnpackRawBytes vgRaw \Network, 61, vgRemaining \IntX:=UDINT;
          IF vgCount = 7 THEN
            UnpackRawBytes vgRaw \Network, 57, vgWord \IntX:=UDINT;
            IF vgWord <> VG_SCALE THEN
              ErrWrite "vgripd", "vgripd sends int32 values, this program reads float32";
              Stop;
            ENDIF
            FOR vgI FROM 1 TO 7 DO
              UnpackRawBytes vgRaw \Network, 21 + 4 * vgI, vgValue{vgI} \Float4;
            ENDFOR
            vgOffset.trans := [vgValue{1}, vgValue{2}, vgValue{3}];
            vgOffset.rot := NOrient([vgValue{4}, vgValue{5}, vgValue{6}, vgValue{7}]);
          ENDIF
          UnpackRawBytes vgRaw \Network, 9, vgStatus \IntX:=UDINT;
          RETURN vgStatus;
        ENDIF
      ENDIF
    ENDWHILE
    RETURN -1;
  ERROR
    IF ERRNO = ERR_SOCK_TIMEOUT OR ERRNO = ERR_SOCK_CLOSED THEN
      RETURN -1;
    ENDIF
    RAISE;
  ENDFUNC

  ! After a failure: drop the connection, the next request opens it again.
  PROC vgClose()
    SocketClose vgSocket;
    vgConnected := FALSE;
  ENDPROC
ENDMODULE

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

  ! One request (VG_LOCATE, VG_NEXT, or VG_CAPTURE_AT with the pose in vgAt): the status of
  ! its final answer, or -1 when none came in time.
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
    ELSE
      SocketSend vgSocket \RawData:=vgRaw;
    ENDIF
    WHILE TRUE DO
      ClearRawBytes vgRaw;
      SocketReceive vgSocket \RawData:=vgRaw \ReadNoOfBytes:=64 \Time:=VG_TIMEOUT_S;
      UnpackRawBytes vgRaw \Network, 1, vgKind \IntX:=UDINT;
      IF vgKind <> VG_CAPTURED AND vgKind <> VG_RESULT AND vgKind <> VG_REFUSED THEN
        RETURN -1; ! not a vgripd answer: the stream is out of step
      ENDIF
      UnpackRawBytes vgRaw \Network, 5, vgWord \IntX:=UDINT;
      IF vgWord = vgId THEN
        IF vgKind = VG_CAPTURED THEN
          vgCaptured := TRUE; ! the images are taken: a robot-mounted camera may move on
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

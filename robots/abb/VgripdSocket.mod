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

  ! Ask vgripd for the offset and return the status; 1 or 2: vgOffset is set.
  FUNC num vgLocate(num vgRecipe)
    RETURN vgAsk(VG_LOCATE, vgRecipe);
  ENDFUNC

  ! The next object of the last vgLocate's pick list (no new image); 10: none left.
  FUNC num vgNext()
    RETURN vgAsk(VG_NEXT, 0);
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

  ! One request (VG_LOCATE or VG_NEXT): the status of its final answer, or -1 when none came
  ! in time.
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
    SocketSend vgSocket \RawData:=vgRaw;
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
